"""Tests of texelbake.cpm."""
