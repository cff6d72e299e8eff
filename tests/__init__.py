"""The test suite: one folder per package of the code, helpers in tests/helpers."""
