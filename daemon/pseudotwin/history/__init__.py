"""History: the store, imports and conversions into it, backfill out of it."""
