"""Small utilities: the single instantiate call site, run records, seeding, environment info."""
