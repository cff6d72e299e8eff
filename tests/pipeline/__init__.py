"""Tests of the bake pipeline end to end, its CLI commands and quality gate."""
