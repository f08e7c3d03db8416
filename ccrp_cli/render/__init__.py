"""Renderers: inventory + address plan + PKI -> every file a clone and a robot need."""
