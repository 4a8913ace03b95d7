"""Task adapter for fringe decoding: one measurement folder -> one zarr store."""

from __future__ import annotations

from prefect import get_run_logger, task

from fringecal.fringe.decode import DecodeSettings
from fringecal.fringe.measurement import decode_folder
from fringecal.tasks.refs import Ref, cache_key, ref_for


def _key(context, parameters) -> str:
    p = parameters
    return cache_key("decode", {"frames": p["frames"], "out": p["out"], "settings": p.get("settings"),
                                "store_frames": p.get("store_frames", False), "attrs": p.get("attrs")},
                     ("fringecal.fringe.measurement",))


@task(name="decode", cache_key_fn=_key, persist_result=True)
def decode_task(frames: Ref, out: str, settings: dict | None = None, store_frames: bool = False,
                attrs: dict | None = None) -> Ref:
    """Decode the frame folder ``frames`` into the store ``out``; the cache key is the
    frames' digest (files and sequence.yaml), the settings and the decoder's source."""
    result = decode_folder(frames.path, out, DecodeSettings(**(settings or {})),
                           attrs={"frames_digest": frames.digest, **(attrs or {})},
                           store_frames=store_frames)
    get_run_logger().info("%s -> %s: %.1f %% valid", frames.path, out, 100 * float(result.valid.mean()))
    return ref_for(out, "store")
