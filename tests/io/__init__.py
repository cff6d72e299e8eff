"""Tests of the artifact store and the plumbing (atomic writes, archives, images)."""
