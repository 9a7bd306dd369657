"""Per-bus scheduling: a sans-I/O core and the asyncio pump that runs it on python-can."""
