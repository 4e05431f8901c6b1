"""Resume: what made a run (its key) and whether its folder still holds that run.

A run is done when its folder's ``run.json`` says ``finished`` (written last) and its ``batch_key.json`` matches what
would make it now (source path, size and content fingerprint, frames, format, the run's config without its thread count,
the vtr version, and for a repeat its teach's key): a changed manifest reruns what changed, and the summary says what
changed. A finished run whose key changed is rerun beside it (``OUT/<route>/.vtr-rerun-<run>/``) and moved in only when
the rerun finished; anything else has the files vtr made in its folder removed and runs again. See the README's
"Batches" section and ``docs/outputs.md``.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from ... import __version__
from ...io.outputs import check_no_links
from ..fingerprint import source_fingerprint
from ..outputs import OutputFolder
from .layout import KEY_NAME, RERUN_PREFIX
from .manifest import RunSpec, run_config


def run_key(
    spec: RunSpec, teach_key: dict[str, Any] | None = None, earlier_keys: list[dict[str, Any]] | None = None
) -> dict[str, Any]:
    """What makes a run's result: its source (path, files, bytes, and a fingerprint of their content:
    :func:`vtr.app.fingerprint.source_fingerprint`), frames, format, config (without the thread count: results are
    identical for every count), the vtr version; a repeat's teach key too, and the keys of the earlier repeats whose
    experiences it builds on (one of them changed: it reruns too)."""
    config = run_config(spec, None).to_dict()
    config.get("features", {}).pop("threads", None)
    src = spec.source.resolve()
    files = [src] if src.is_file() else [f for f in src.rglob("*") if f.is_file()]
    key: dict[str, Any] = {
        "source": str(src),
        "source_files": len(files),
        "source_bytes": sum(f.stat().st_size for f in files),
        "source_content": source_fingerprint(src),
        "frames": spec.frames,
        "format": spec.fmt,
        "config": hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode()).hexdigest(),
        "version": __version__,
    }
    if teach_key is not None:
        key["teach"] = hashlib.sha256(json.dumps(teach_key, sort_keys=True).encode()).hexdigest()
    if earlier_keys:
        key["experiences"] = hashlib.sha256(json.dumps(earlier_keys, sort_keys=True).encode()).hexdigest()
    return key


def key_change(folder: Path, key: dict[str, Any]) -> str | None:
    """None when ``folder``'s run was made with ``key``; else what changed (for the summary)."""
    try:
        data = OutputFolder(folder).read_own(KEY_NAME)  # never through a link vtr did not make
        old = None if data is None else json.loads(data)
    except (OSError, ValueError):
        old = None
    if not isinstance(old, dict):
        return "no record of what made it"
    diff = [k for k in key if old.get(k) != key[k]]
    if not diff:
        return None
    names = {"source_files": "source", "source_bytes": "source", "source_content": "source", "teach": "its teach"}
    what = sorted({names.get(k, k) for k in diff})
    detail = f" ({old.get('frames')!r} -> {key['frames']!r})" if "frames" in diff else ""
    return f"rerun: {', '.join(what)} changed{detail}"


def rerun_folder(out: Path, spec: RunSpec) -> Path:
    return Path(out) / spec.route / f"{RERUN_PREFIX}{spec.name}"


def prepare_run_folder(out: Path, spec: RunSpec, folder: Path | None = None) -> OutputFolder:
    """The run's folder inside ``out`` (or ``folder``, its rerun folder) without what an earlier attempt made
    (only the files vtr recorded there; never through a symbolic link: ``OutputError``)."""
    folder = spec.folder(out) if folder is None else folder
    check_no_links(out, folder)
    folder.mkdir(parents=True, exist_ok=True)
    check_no_links(out, folder)
    own = OutputFolder(folder)
    own.clear()
    return own
