"""Typed records at the edges: the inventory (desired fleet) and the state (what exists)."""
