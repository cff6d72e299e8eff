import os

import numpy as np
import pytest

os.environ.setdefault("OMP_NUM_THREADS", "2")


@pytest.fixture(scope="session", autouse=True)
def _artifact_store(tmp_path_factory):
    """Local bakes keep their artifacts outside the output folder (issue 22): in tests, in
    one store per session rather than the user's cache."""
    old = os.environ.get("TEXELBAKE_WORKDIR")
    os.environ["TEXELBAKE_WORKDIR"] = str(tmp_path_factory.mktemp("artifacts"))
    yield
    if old is None:
        os.environ.pop("TEXELBAKE_WORKDIR", None)
    else:
        os.environ["TEXELBAKE_WORKDIR"] = old


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
