"""Tests of texelbake.btf."""
