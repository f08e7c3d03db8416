"""Fleet operations: what `ccrp` does to clones and snapshots through a provider (create, reconcile,
bake, gc, doctor, quotas, init, deploy)."""
