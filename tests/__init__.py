"""The test suite: one folder per package of the code, helpers in tests/helpers.

Every folder is a Python package (an `__init__.py`), so pytest's default import mode puts the
repository root on sys.path (`from tests.helpers.render import ...` works under `pytest` and
`python -m pytest`) and test files of the same name in different folders
(tests/srf/test_store.py, tests/io/test_store.py) import as different modules."""
