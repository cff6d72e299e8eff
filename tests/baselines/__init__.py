"""Tests of the filtered baseline maps (LEAN/LEADR moments, Toksvig, AO)."""
