"""File plumbing: the artifact store, per-sample spools, passes a chunk at a time, the one
atomic write, deterministic archives and the one way to read and write images."""
