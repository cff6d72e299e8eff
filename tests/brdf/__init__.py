"""Tests of texelbake.brdf."""
