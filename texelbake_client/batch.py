"""`texelbake submit --manifest FILE`: many assets as one batch (`POST /api/v1/batches`).

The manifest is JSON::

    {"name": "props",                        optional
     "settings": {"atlas_resolution": 64},   optional: defaults of every item (BakeSettings)
     "priority": 50,                         optional: 0..100, default of every item
     "items": [{"path": "crate.usda"},       a layer file, a folder, a .usdz or a .zip
               {"path": "barrel", "settings": {"samples_per_texel": 32}, "priority": 80}]}

`path` is relative to the manifest's folder; an item's `settings` override the batch's field
by field. Every item is uploaded (`texelbake_client.submit.upload`), the batch is created, its
progress shown on one line, and when every item has finished the batch archive is unpacked
into the output folder: `batch.json` and one folder per succeeded item. Uses only httpx and
the standard library (no server imports).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx

from texelbake.errors import SettingsError, StageError
from texelbake_client.submit import API, ProgressBar, check_response, safe_extract, upload

MANIFEST_KEYS = frozenset({"name", "settings", "priority", "items"})
ITEM_KEYS = frozenset({"path", "settings", "priority"})
FINISHED = ("succeeded", "failed", "cancelled")


@dataclass
class Manifest:
    """A parsed manifest: item paths resolved against the manifest's folder."""

    paths: list[Path]
    body: dict[str, Any]  # the `POST /batches` body without the items' asset ids
    items: list[dict[str, Any]]  # per item: its `settings` and `priority`, if given


def load_manifest(path: str | Path) -> Manifest:
    """Read and check a manifest's shape (the server checks the settings themselves)."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except OSError as exc:
        raise SettingsError(f"manifest {path}: cannot read it: {exc}") from exc
    except json.JSONDecodeError as exc:
        raise SettingsError(f"manifest {path}: not JSON: {exc}") from exc
    if not isinstance(doc, dict):
        raise SettingsError(f"manifest {path}: expected a JSON object")
    extra = set(doc) - MANIFEST_KEYS
    if extra:
        raise SettingsError(f"manifest {path}: unknown keys {sorted(extra)}; "
                            f"expected {sorted(MANIFEST_KEYS)}")
    items = doc.get("items")
    if not isinstance(items, list) or not items:
        raise SettingsError(f"manifest {path}: `items` must be a non-empty list")
    body = {k: doc[k] for k in ("name", "settings", "priority") if k in doc}
    paths, out = [], []
    for i, item in enumerate(items):
        if not isinstance(item, dict) or not isinstance(item.get("path"), str):
            raise SettingsError(f"manifest {path}: items[{i}] needs a string `path`")
        extra = set(item) - ITEM_KEYS
        if extra:
            raise SettingsError(f"manifest {path}: items[{i}]: unknown keys {sorted(extra)}; "
                                f"expected {sorted(ITEM_KEYS)}")
        p = Path(item["path"])
        p = p if p.is_absolute() else path.parent / p
        if not p.exists():
            raise SettingsError(f"manifest {path}: items[{i}]: {p} does not exist")
        paths.append(p)
        out.append({k: item[k] for k in ("settings", "priority") if k in item})
    return Manifest(paths, body, out)


def _label(batch: dict[str, Any]) -> str:
    c = batch["counts"]
    done = c["succeeded"] + c["failed"] + c["cancelled"]
    parts = [f"{c[k]} {k}" for k in ("running", "queued", "succeeded", "failed", "cancelled")
             if c[k]]
    return f"{done}/{c['total']} items: {', '.join(parts)}"


def submit_batch(
    manifest: str | Path,
    server: str,
    token: str,
    out_dir: str | Path,
    *,
    progress: bool = True,
    poll: float = 1.0,
    timeout: float = 24 * 3600.0,
    on_status: Any = None,
    transport: httpx.BaseTransport | None = None,
) -> dict[str, Any]:
    """Upload every item of `manifest`, create the batch, follow it on one progress line,
    unpack its archive into `out_dir`. Returns the finished batch (`BatchPublic` JSON);
    items that failed or were cancelled are in it with their errors (the caller decides
    what that means). Raises StageError when an upload or the batch is refused (naming the
    item), or the batch does not finish within `timeout`."""
    m = load_manifest(manifest)
    deadline = time.monotonic() + timeout
    bar = ProgressBar(progress)
    with httpx.Client(base_url=server.rstrip("/"), headers={"Authorization": f"Bearer {token}"},
                      timeout=120.0, transport=transport) as c:
        uploaded: dict[Path, str] = {}
        items = []
        for i, (p, extra) in enumerate(zip(m.paths, m.items, strict=True)):
            key = p.resolve()
            if key not in uploaded:
                uploaded[key] = upload(c, p, f"items[{i}] ({p})")["id"]
            items.append({"asset_id": uploaded[key], **extra})
        batch = check_response(c.post(f"{API}/batches", json={**m.body, "items": items}),
                       "create batch").json()
        try:
            while batch["state"] not in FINISHED:
                bar.show(batch["progress"], _label(batch))
                if on_status is not None:
                    on_status(batch)
                if time.monotonic() > deadline:
                    raise StageError(f"batch {batch['id']} did not finish within {timeout} s")
                time.sleep(poll)
                try:
                    batch = check_response(c.get(f"{API}/batches/{batch['id']}"), "batch status").json()
                except httpx.TransportError:
                    continue  # the API is restarting: ask again
            bar.show(batch["progress"], _label(batch))
        finally:
            bar.close()
        r = check_response(c.get(f"{API}/batches/{batch['id']}/result"), "download batch result")
    safe_extract(r.content, Path(out_dir))
    return batch


def failed_items(batch: dict[str, Any], paths: list[Path] | None = None) -> list[str]:
    """One line per item that did not succeed: index, path (when given), state, error."""
    out = []
    for it in batch["items"]:
        if it["state"] != "succeeded":
            where = f" {paths[it['index']]}" if paths else ""
            out.append(f"items[{it['index']}]{where}: {it['state']}: {it.get('error') or '-'}")
    return out
