// A PLC's session with cellctl's OPC UA for Machine Vision server, in node-opcua (another OPC UA stack
// than the server's). Usage: node scenario.js <endpoint-url>. Prints one JSON object per line, each
// with a "step" (tests/plc/test_opcua_machine_vision.py asserts on them); exits 1 on a failure.
//
// browse -> SelectModeAutomatic -> GetRecipeListFiltered -> PrepareRecipe("1") -> subscribe to
// VisionSystem's events -> StartSingleJob -> its ResultReady event -> GetResultById ->
// StartContinuous -> a result per cycle -> Stop -> Ready -> GetResultListFiltered(JobId) ->
// a wrong argument type -> Halt -> Reset.
"use strict";
const {
  OPCUAClient, AttributeIds, DataType, VariantArrayType, makeBrowsePath, constructEventFilter,
  ClientMonitoredItem, TimestampsToReturn, NodeId, NodeIdType, coerceNodeId, MessageSecurityMode, SecurityPolicy,
} = require("node-opcua-client");

const MV = "http://opcfoundation.org/UA/MachineVision";
const url = process.argv[2];
const out = (step, data) => console.log(JSON.stringify({ step, ...data }));
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

async function main() {
  const client = OPCUAClient.create({
    endpointMustExist: false, securityMode: MessageSecurityMode.None, securityPolicy: SecurityPolicy.None,
    connectionStrategy: { maxRetry: 2, initialDelay: 500 }, requestedSessionTimeout: 600000,
    defaultTransactionTimeout: 120000,
  });
  await client.connect(url);
  const session = await client.createSession();
  try {
    await scenario(session);
  } finally {
    await session.close();
    await client.disconnect();
  }
}

async function scenario(session) {
  // VisionSystem is added once the server listens: wait until its state is shown (up to 60 s).
  let ns = -1;
  const built = Date.now() + 60000;
  for (;;) {
    ns = (await session.read({ nodeId: "i=2255", attributeId: AttributeIds.Value })).value.value.indexOf(MV);
    if (ns >= 0) {
      const r = await session.translateBrowsePath(makeBrowsePath("i=85",
        `/${ns}:VisionSystem/${ns}:VisionStateMachine/CurrentState`));
      const dv = r.targets && r.targets.length ? await session.read({ nodeId: r.targets[0].targetId }) : null;
      if (dv && dv.value.value && dv.value.value.text) break;
    }
    if (Date.now() > built) throw new Error("no VisionSystem within 60 s");
    await sleep(200);
  }
  const q = (name) => `/${ns}:${name}`;
  const resolve = async (path) => {
    const r = await session.translateBrowsePath(makeBrowsePath("i=85", path));
    if (!r.targets || r.targets.length === 0) throw new Error(`${path}: ${r.statusCode.name}`);
    return r.targets[0].targetId;
  };
  const vs = await resolve(q("VisionSystem"));
  const vsm = await resolve(q("VisionSystem") + q("VisionStateMachine"));
  const auto = await resolve(q("VisionSystem") + q("VisionStateMachine") + q("AutomaticModeStateMachine"));
  const recipes = await resolve(q("VisionSystem") + q("RecipeManagement"));
  const results = await resolve(q("VisionSystem") + q("ResultManagement"));
  const base = q("VisionSystem");
  const m = {
    select: [vsm, await resolve(base + q("VisionStateMachine") + q("SelectModeAutomatic"))],
    halt: [vsm, await resolve(base + q("VisionStateMachine") + q("Halt"))],
    reset: [vsm, await resolve(base + q("VisionStateMachine") + q("Reset"))],
    single: [auto, await resolve(base + q("VisionStateMachine") + q("AutomaticModeStateMachine") + q("StartSingleJob"))],
    continuous: [auto, await resolve(base + q("VisionStateMachine") + q("AutomaticModeStateMachine") + q("StartContinuous"))],
    stop: [auto, await resolve(base + q("VisionStateMachine") + q("AutomaticModeStateMachine") + q("Stop"))],
    prepare: [recipes, await resolve(base + q("RecipeManagement") + q("PrepareRecipe"))],
    recipeList: [recipes, await resolve(base + q("RecipeManagement") + q("GetRecipeListFiltered"))],
    byId: [results, await resolve(base + q("ResultManagement") + q("GetResultById"))],
    list: [results, await resolve(base + q("ResultManagement") + q("GetResultListFiltered"))],
  };
  const call = async (which, inputArguments = []) => {
    const [objectId, methodId] = m[which];
    const r = await session.call({ objectId, methodId, inputArguments });
    return { status: r.statusCode.name, out: (r.outputArguments || []).map((v) => v.value) };
  };
  const state = async (node) => {
    const dv = await session.read({ nodeId: await resolve(pathOf(node) + "/CurrentState"), attributeId: AttributeIds.Value });
    return dv.value.value ? dv.value.value.text : null;
  };
  const pathOf = (node) => (node === vsm ? base + q("VisionStateMachine")
    : base + q("VisionStateMachine") + q("AutomaticModeStateMachine"));
  const struct = (id, fields) => session.constructExtensionObject(coerceNodeId(`ns=${ns};i=${id}`), fields);
  const ext = (value) => ({ dataType: DataType.ExtensionObject, value });
  const nullExt = { dataType: DataType.ExtensionObject, value: null };
  const noParams = { dataType: DataType.Variant, arrayType: VariantArrayType.Array, value: [] };
  const cause = [{ dataType: DataType.Int32, value: 0 }, { dataType: DataType.LocalizedText, value: { text: "PLC" } }];
  const idOf = (s) => (s && (s.id !== undefined ? s.id : s.Id));

  // Browse: the VisionSystem's children and its state.
  const children = (await session.browse(vs)).references.map((r) => r.browseName.name).sort();
  out("browse", { ns, children, vision_state: await state(vsm), auto_state: await state(auto) });

  out("select", { ...(await call("select")), auto_state: await state(auto) });
  const list = await call("recipeList", [nullExt, nullExt, { dataType: DataType.Int32, value: 2 },
    { dataType: DataType.UInt32, value: 0 }, { dataType: DataType.UInt32, value: 0 }, { dataType: DataType.Int32, value: 1000 }]);
  out("recipes", { status: list.status, ids: (list.out[3] || []).map(idOf) });
  const prepared = await call("prepare", [ext(await struct(3002, { id: "1" })), nullExt]);
  out("prepare", { status: prepared.status, internal_id: idOf(prepared.out[0]), auto_state: await state(auto) });

  // Events from VisionSystem.
  const fields = ["EventType", "ResultId", "JobId", "ResultState", "IsPartial", "CreationTime", "InternalRecipeId",
    "InternalConfigurationId", "ResultContent"];
  const sub = await session.createSubscription2({ requestedPublishingInterval: 100, publishingEnabled: true,
    requestedLifetimeCount: 6000, requestedMaxKeepAliveCount: 20 });
  const item = ClientMonitoredItem.create(sub, { nodeId: vs, attributeId: AttributeIds.EventNotifier },
    { queueSize: 1000, discardOldest: false, filter: constructEventFilter(fields.map((f) => (f === "EventType" ? f : `${ns}:${f}`))) },
    TimestampsToReturn.Both);
  const events = [];
  item.on("changed", (values) => {
    const e = {};
    fields.forEach((f, i) => { e[f] = values[i].value; });
    events.push({ result_id: idOf(e.ResultId), job_id: idOf(e.JobId), result_state: e.ResultState, is_partial: e.IsPartial,
      creation_time: e.CreationTime, recipe: idOf(e.InternalRecipeId), configuration: idOf(e.InternalConfigurationId),
      content: Array.isArray(e.ResultContent) ? e.ResultContent.map((v) => (v && v.value !== undefined ? v.value : v)) : e.ResultContent });
  });
  await sleep(500);
  const waitFor = async (check, ms) => {
    const end = Date.now() + ms;
    while (Date.now() < end) { const hit = check(); if (hit) return hit; await sleep(100); }
    return null;
  };

  // One job: a pick.
  const job = await call("single", [ext(await struct(3015, { id: "M-1" })), nullExt, nullExt, nullExt, noParams]);
  const jobId = idOf(job.out[0]);
  out("single", { status: job.status, job_id: jobId, auto_state: await state(auto) });
  const ev = await waitFor(() => events.find((e) => e.job_id === jobId), 90000);
  out("single_event", { event: ev });
  await sleep(300);
  out("single_done", { auto_state: await state(auto) });
  if (ev) {
    const got = await call("byId", [ext(await struct(3021, { id: ev.result_id })), { dataType: DataType.Int32, value: 1000 }]);
    const r = got.out[1] || {};
    out("result", { status: got.status, result_id: idOf(r.resultId), job_id: idOf(r.jobId), result_state: r.resultState,
      content: (r.resultContent || []).map((v) => (v && v.value !== undefined ? v.value : v)) });
  }

  // Continuous: a result per cycle until Stop.
  // Parameters: one KeyValuePair Count (more parts than the Stop lets it place).
  const countParam = await session.constructExtensionObject(coerceNodeId("i=14533"),
    { key: { namespaceIndex: 0, name: "Count" }, value: { dataType: DataType.Int32, value: 5 } });
  const run = await call("continuous", [nullExt, nullExt, nullExt, nullExt,
    { dataType: DataType.ExtensionObject, arrayType: VariantArrayType.Array, value: [countParam] }]);
  const runJob = idOf(run.out[0]);
  out("continuous", { status: run.status, job_id: runJob, auto_state: await state(auto) });
  const first = await waitFor(() => events.find((e) => e.job_id === runJob), 120000);
  const stopped = await call("stop", cause);
  let ended = null;
  const end = Date.now() + 120000;
  while (Date.now() < end) { const s = await state(auto); if (s !== "ContinuousExecution") { ended = s; break; } await sleep(200); }
  await sleep(500);
  const runEvents = events.filter((e) => e.job_id === runJob);
  const filtered = await call("list", [{ dataType: DataType.Int32, value: 0 }, nullExt, nullExt, nullExt, nullExt, nullExt,
    nullExt, nullExt, ext(await struct(3016, { id: runJob })), { dataType: DataType.UInt32, value: 0 },
    { dataType: DataType.UInt32, value: 0 }, { dataType: DataType.Int32, value: 1000 }]);
  out("continuous_done", { first: Boolean(first), stop: stopped.status, auto_state: ended,
    events: runEvents.map((e) => ({ result_id: e.result_id, result_state: e.result_state, content: e.content })),
    list_status: filtered.status, listed: (filtered.out[3] || []).map((r) => idOf(r.resultId)) });

  // A wrong argument type: refused, nothing runs.
  const bad = await call("single", [{ dataType: DataType.Int32, value: 7 }, nullExt, nullExt, nullExt, noParams]);
  out("bad_argument", { status: bad.status, auto_state: await state(auto) });

  // Halt latches the robot; Reset leaves Halted.
  const halt = await call("halt", cause);
  out("halt", { status: halt.status, vision_state: await state(vsm), auto_state: await state(auto) });
  const reset = await call("reset", cause);
  await sleep(500);
  out("reset", { status: reset.status, vision_state: await state(vsm) });
  await sub.terminate();
}

main().then(() => process.exit(0), (err) => { out("error", { message: String(err && err.stack || err) }); process.exit(1); });
