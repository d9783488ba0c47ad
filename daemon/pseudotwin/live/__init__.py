"""The live path: readings → window → models → twin (one pseudo-measurement stream)."""
