import os

import pytest

# Under pytest-xdist (`make test` runs two workers) each worker gets its share of the cores, so
# two torch/OpenMP pools do not oversubscribe the machine (OpenMP's spin-waits then cost more
# than the parallelism gains).
_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
os.environ.setdefault("OMP_NUM_THREADS", str(max(1, (os.cpu_count() or 2) // _WORKERS)))

#: tests that start real processes (an API, Redis, Celery workers, Chromium) run one after
#: another on one xdist worker: their waits overlap the other worker's numerical tests, but no
#: two farms compete, so their time limits mean what they say on a loaded machine
_FARM_MARKERS = ("service", "browser")


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """With `--dist loadgroup`, a module's tests stay together on one worker (its module
    fixtures are built once) and the farm tests form one group (see `_FARM_MARKERS`)."""
    # an xdist worker runs with `dist` "no" and keeps the choice in `loadgroup`; the worker
    # is where the marks count (it names each test's group in the ids it sends)
    if config.getoption("dist", "no") != "loadgroup" and not getattr(config.option,
                                                                         "loadgroup", False):
        return
    for item in items:
        farm = any(item.get_closest_marker(m) for m in _FARM_MARKERS)
        item.add_marker(pytest.mark.xdist_group("farm" if farm else item.module.__name__))


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
    # numpy imported here, not at the top: the xdist controller loads this file and runs no
    # test, so it need not load numpy (and its OpenBLAS threads) at all
    import numpy as np

    return np.random.default_rng(12345)
