"""What every run of :mod:`vtr.app.pipeline` starts from: its frozen inputs (:class:`RunInputs`), the first step
(:func:`open_inputs`: the source open, its frames selected, the outputs prepared) and the frames behind a progress
bar (docs/architecture.md)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..config import Config
from ..io import open_source, parse_frame_range
from ..io.base import FrameSource, SourceOptions
from ..types import StereoFrame
from ..vo.stereo import StereoProcessor
from .outputs import OutputFolder
from .runfiles.run_json import RunLog

#: a progress-bar factory (e.g. tqdm): ``progress(items, total=n, desc="odometry")`` yields the items
Progress = Callable[..., Iterable[Any]]


@dataclass(frozen=True)
class RunInputs:
    """What every run reads: the source (with its reader's options), the frames selected (``"0::2"``; None: all),
    the configuration, and where its progress goes."""

    source_path: Path
    frames: str | None
    config: Config
    source_options: SourceOptions | str | None = None
    progress: Progress | None = None


@dataclass(frozen=True)
class OpenSource:
    """The first step of every run: the source open, its selected frame indices, the output folder (None: a teach
    without ``--out``) and the run's log."""

    source: FrameSource
    indices: list[int]
    folder: OutputFolder | None
    log: RunLog | None


def open_inputs(
    stack: ExitStack,
    inputs: RunInputs,
    command: str,
    out: Path | None,
    outputs: Sequence[str],
    extra_inputs: Sequence[Path] = (),
) -> OpenSource:
    """Open ``inputs``' source on ``stack``, select its frames and prepare ``out`` for ``outputs`` (checked before
    any work)."""
    source = stack.enter_context(open_source(inputs.source_path, inputs.source_options))
    indices = parse_frame_range(inputs.frames, len(source), str(inputs.source_path))
    if out is None:
        return OpenSource(source, indices, None, None)
    folder = OutputFolder.prepare(out, [inputs.source_path], outputs)
    return OpenSource(source, indices, folder, RunLog(out, command, inputs.config, [inputs.source_path, *extra_inputs]))


def iterate(items: Iterable[Any], total: int, progress: Progress | None, desc: str) -> Iterable[Any]:
    """Wrap an iterable with a progress bar factory (e.g. tqdm) when given."""
    return progress(items, total=total, desc=desc) if progress else items


def frames_of(
    source: FrameSource, indices: list[int], processor: StereoProcessor, progress: Progress | None, desc: str
) -> Iterable[StereoFrame]:
    """The selected frames of ``source`` as stereo frames, behind the progress bar; with ``features.threads``
    of 2 or more the next ones are decoded and stereo-processed in the background
    (:meth:`StereoProcessor.frames`)."""
    return iterate(processor.frames(source.iter_frames(indices)), len(indices), progress, desc)
