"""Tests of the cost model and the machine-speed reading."""
