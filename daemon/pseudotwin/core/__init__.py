"""Time and data primitives: operating hours and the slot grid, day series of readings."""
