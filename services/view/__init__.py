"""``crosspath view``: the run in the browser, live over Zenoh or replayed from a trace."""
