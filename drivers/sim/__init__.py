"""The virtual cell: a simulated camera and robot sharing one rendered world (a product, not a mock)."""
