"""xatlas packs in a child process, so that a hang inside xatlas cannot hang a bake.

xatlas 0.0.11's `Atlas` runs a task scheduler of worker threads, and its destructor
(`xatlas::Destroy`, joining them) has been seen to wait forever, nondeterministically: a
farm worker, a `cpm_cpu.py` run and a test's geometry stage each stopped there at 0 % CPU
(py-spy: `std::thread::join` under `TaskScheduler::~TaskScheduler`). The race is inside the
library, which the Python binding gives no way to configure (thread count, scheduler). So the
packs run in one long-lived child (this file run as a script, a plain subprocess: a Celery
prefork worker is a daemonic process and may not start multiprocessing
children), one request at a time over pipes. The child answers a pack before it drops the
`Atlas`, and acknowledges the drop after; a drop not acknowledged within `DROP_SECONDS` kills
the child (the answer is already in hand) and the next pack starts a new one. A pack not
answered within `PACK_SECONDS` kills the child and is tried again in a new one, up to
`PACK_TRIES` times; xatlas is deterministic, so the answer does not depend on which child
gave it.

Protocol: length-prefixed pickles. Request (vertices float32 (v, 3), faces uint32 (f, 3),
resolution, padding, texels_per_unit); answer (atlas_count, width, height, vmap, indices,
uvs of the first mesh), then the byte b"D" once the `Atlas` is dropped.
"""

from __future__ import annotations

import os
import pickle
import select
import struct
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np

from texelbake.errors import StageError

#: seconds a pack may take before its child is taken to hang (the full bolt's LOD1, 8k faces,
#: packs in ~4 s on this machine)
PACK_SECONDS = 600.0
#: seconds the child may take to drop an `Atlas` after answering (milliseconds when it works)
DROP_SECONDS = 20.0
#: children a pack is tried in before the geometry stage fails
PACK_TRIES = 3


@dataclass(frozen=True)
class Packed:
    """What the geometry stage reads of an xatlas `Atlas`: its page count and size, and its
    first mesh's (vertex map (n,) uint32, indices (f, 3) uint32, uvs (n, 2) float32)."""

    atlas_count: int
    width: int
    height: int
    mesh: tuple[np.ndarray, np.ndarray, np.ndarray]

    def __getitem__(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if i != 0:
            raise IndexError("one mesh per atlas")
        return self.mesh


def _pack(vertices: np.ndarray, faces: np.ndarray, resolution: int, padding: int,
          tpu: float):
    import xatlas  # the child's only use of it

    atlas = xatlas.Atlas()
    atlas.add_mesh(np.ascontiguousarray(vertices, dtype=np.float32),
                   np.ascontiguousarray(faces, dtype=np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = int(resolution)
    pack.padding = int(padding)
    pack.bilinear = True
    pack.texels_per_unit = float(tpu)
    atlas.generate(pack_options=pack)
    return atlas


def _send(fd, obj) -> None:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    fd.write(struct.pack("<Q", len(data)) + data)
    fd.flush()


def _read_exact(fd: int, n: int, deadline: float) -> bytes:
    buf = b""
    while len(buf) < n:
        left = deadline - time.monotonic()
        if left <= 0 or not select.select([fd], [], [], left)[0]:
            raise TimeoutError
        chunk = os.read(fd, n - len(buf))
        if not chunk:
            raise EOFError
        buf += chunk
    return buf


class _Child:
    """The running child process and its pipes."""

    def __init__(self) -> None:
        # this file run as a script (it imports numpy, xatlas and texelbake.errors only),
        # texelbake from the tree this module is in
        root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        path = os.pathsep.join([root, *filter(None, [os.environ.get("PYTHONPATH")])])
        self.proc = subprocess.Popen([sys.executable, os.path.abspath(__file__)],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     env={**os.environ, "PYTHONPATH": path})
        self.dropped = True  # the previous pack's Atlas acknowledged dropped
        self.owner = os.getpid()  # a forked process starts its own child, never shares this

    def kill(self) -> None:
        self.proc.kill()
        self.proc.wait()

    def request(self, args: tuple) -> Packed:
        out = self.proc.stdout.fileno()  # type: ignore[union-attr]
        if not self.dropped:  # the last drop's acknowledgement
            if _read_exact(out, 1, time.monotonic() + DROP_SECONDS) != b"D":
                raise EOFError
            self.dropped = True
        _send(self.proc.stdin, args)
        deadline = time.monotonic() + PACK_SECONDS
        (size,) = struct.unpack("<Q", _read_exact(out, 8, deadline))
        answer = pickle.loads(_read_exact(out, size, deadline))
        self.dropped = False
        if isinstance(answer, str):
            raise StageError(f"geometry: xatlas failed: {answer}")
        count, width, height, vmap, indices, uvs = answer
        return Packed(int(count), int(width), int(height), (vmap, indices, uvs))


_lock = threading.Lock()
_child: _Child | None = None


def xatlas_pack(vertices: np.ndarray, faces: np.ndarray, resolution: int, padding: int,
                tpu: float) -> Packed:
    """One xatlas pack of a mesh (module docstring): page `resolution` (0: unbounded),
    `padding` texels, `tpu` texels per unit; raises StageError when PACK_TRIES children hang."""
    global _child
    args = (np.ascontiguousarray(vertices, dtype=np.float32),
            np.ascontiguousarray(faces, dtype=np.uint32), int(resolution), int(padding),
            float(tpu))
    with _lock:
        for _ in range(PACK_TRIES):  # loop over children: a hung one is replaced
            if _child is None or _child.owner != os.getpid() or _child.proc.poll() is not None:
                _child = _Child()
            try:
                return _child.request(args)
            except (TimeoutError, EOFError, OSError):
                _child.kill()
                _child = None
        raise StageError(f"geometry: xatlas hung or died on M1 ({len(faces)} faces) in "
                         f"{PACK_TRIES} processes in a row")


def _serve() -> None:
    """The child's loop: a pack per request, answered, then its Atlas dropped and the drop
    acknowledged."""
    inp, out = sys.stdin.buffer, sys.stdout.buffer
    while True:  # loop over requests until the parent closes the pipe
        head = inp.read(8)
        if len(head) < 8:
            return
        (size,) = struct.unpack("<Q", head)
        vertices, faces, resolution, padding, tpu = pickle.loads(inp.read(size))
        try:
            atlas = _pack(vertices, faces, resolution, padding, tpu)
            vmap, indices, uvs = atlas[0]
            _send(out, (atlas.atlas_count, atlas.width, atlas.height, vmap, indices, uvs))
        except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises
            _send(out, f"{type(exc).__name__}: {exc}")
            atlas = None
        del atlas  # xatlas::Destroy: where the library has hung
        out.write(b"D")
        out.flush()


if __name__ == "__main__":
    _serve()
