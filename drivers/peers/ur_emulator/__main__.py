"""``python -m drivers.peers.ur_emulator``: run the UR emulator on 127.0.0.1 until SIGINT/SIGTERM."""

from drivers.peers.ur_emulator.emulator import main

main()
