"""Flow behind ``fringecal decode``: one task per measurement folder."""

from __future__ import annotations

from prefect import flow
from prefect.task_runners import ThreadPoolTaskRunner

from fringecal.store import is_complete
from fringecal.tasks.decode import decode_task
from fringecal.tasks.refs import Ref, ref_for


# One measurement at a time: each decode already uses every core and holds ~1 GB of
# frames (2048 x 2048 x 98 x 16 bit), so running several at once only adds memory.
@flow(name="decode", task_runner=ThreadPoolTaskRunner(max_workers=1))
def decode_flow(frame_dirs: list[str], outs: list[str], settings: dict | None = None,
                store_frames: bool = False) -> list[Ref]:
    """Decode every frame folder into its store; returns the stores' refs in order.

    A store that is missing or incomplete is rebuilt even when the cache has a result
    for the same frames and settings.
    """
    futures = []
    for frames, out in zip(frame_dirs, outs, strict=True):
        task = decode_task.with_options(refresh_cache=not is_complete(out))
        futures.append(task.submit(ref_for(frames, "frames"), out, settings, store_frames))
    return [f.result() for f in futures]
