"""Benchmark: importing one 98-frame 2048 x 2048 measurement from PNG, TIFF and BMP files.

Prints JSON: for each file variant, how fast each candidate library reads the 98 files
into one preallocated (n_frames, H, W) stack with one thread per core (M px of frames
per second, median of ``--repeats``, warm page cache) and how fast the importer
(:func:`fringecal.fringe.importer.read_frames`, with all its checks) does, warm and cold
(the variant's files evicted from the page cache with ``posix_fadvise(DONTNEED)``
before each repeat; other files stay cached). For PNG also the inflate bound: the
files' zlib streams, already in memory, inflated by libdeflate on the same threads
(no file reading, unfiltering or checks), and other inflaters on one thread. Peak RSS
of ``read_frames``, the PNG row filters libpng chose, the load average around every
variant, and an overlap probe (reading and decoding side by side against one after
the other: whether streaming the decode behind the reading could gain anything).

    PYTHONPATH=. python benchmarks/image_import.py [--size 2048] [--repeats 3] [--threads N]
                                                   [--variants png16_vendor,tif_lzw,...] [--out FILE]

``--smoke``: 64 x 64 px, one repeat, the variants png16_fringecal and tif_lzw, the
memory probe (a fresh process) for the first only.

The frames are ``benchmarks/decode.py``'s: 12-bit fringes (A 1500, B 1000 DN) with 8 DN
Gaussian noise in uint16; the 8-bit variants hold the same frames shifted right by 4.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import imagecodecs
import numba as nb
import numpy as np
import tifffile
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import add_options, conditions, finish  # noqa: E402
from decode import make_frames  # noqa: E402 - benchmarks/decode.py, this script's sibling

from fringecal.fringe.decode import decode  # noqa: E402
from fringecal.fringe.frame_files import _png_gather_idat  # noqa: E402
from fringecal.fringe.importer import read_frames, write_frames  # noqa: E402
from fringecal.fringe.sequence import FringeSequence  # noqa: E402

SEQ = FringeSequence()
PNG = imagecodecs.PNG

# variant: (what it is, extension, bits, writer(path, frame) or "write_frames")
VARIANTS = {
    "png16_vendor": ("16-bit grey PNG holding the 12-bit data, libpng (imagecodecs.png_encode) at zlib level 6, "
                     "default strategy, libpng's adaptive row filters: what a vendor writing with libpng's "
                     "defaults produces", "png", 16,
                     lambda p, f: p.write_bytes(imagecodecs.png_encode(f, level=6))),
    "png16_fringecal": ("16-bit PNG as fringecal writes it (write_frames, `fringecal simulate`): OpenCV's "
                        "libpng at zlib level 1, default strategy, adaptive filters", "png", 16, "write_frames"),
    "png16_paeth": ("16-bit PNG, zlib level 6, Paeth filter on every row: the worst case for unfiltering",
                    "png", 16, lambda p, f: p.write_bytes(imagecodecs.png_encode(f, level=6, filter=PNG.FILTER.PAETH))),
    "png8_vendor": ("8-bit grey PNG (the frames >> 4), libpng at zlib level 6, adaptive filters", "png", 8,
                    lambda p, f: p.write_bytes(imagecodecs.png_encode(f, level=6))),
    "tif_none": ("16-bit TIFF, uncompressed, one strip (tifffile)", "tif", 16,
                 lambda p, f: tifffile.imwrite(p, f, compression=None)),
    "tif_lzw": ("16-bit TIFF, LZW with horizontal-difference predictor (tifffile, its default 64 rows per "
                "strip)", "tif", 16, lambda p, f: tifffile.imwrite(p, f, compression="lzw", predictor=True)),
    "tif_deflate": ("16-bit TIFF, deflate (zlib level 6) with horizontal-difference predictor (tifffile, 64 rows "
                    "per strip)", "tif", 16,
                    lambda p, f: tifffile.imwrite(p, f, compression="zlib", compressionargs={"level": 6},
                                                  predictor=True)),
    "bmp8": ("8-bit BMP (the frames >> 4), paletted with the grey identity palette, bottom-up rows "
             "(imagecodecs.bmp_encode; there is no 16-bit grey BMP)", "bmp", 8,
             lambda p, f: p.write_bytes(imagecodecs.bmp_encode(f))),
}


def _optional(name):
    try:
        return importlib.import_module(name)
    except ImportError:
        return None


def candidates(ext):
    """Library candidates for one format: name -> (version, reader(path, out))."""
    cv2, pil, pyspng = _optional("cv2"), _optional("PIL.Image"), _optional("pyspng")
    out = {}
    if cv2 is not None:
        def read_cv2(path, dst):
            img = cv2.imdecode(np.fromfile(path, np.uint8), cv2.IMREAD_UNCHANGED)
            dst[...] = img
        out["opencv imdecode (libpng/libtiff)"] = (cv2.__version__, read_cv2)
    if pil is not None:
        def read_pil(path, dst):
            with pil.open(path) as im:
                dst[...] = np.asarray(im)
        out["Pillow Image.open + asarray"] = (importlib.import_module("PIL").__version__, read_pil)
    if ext == "png":
        out["imagecodecs.png_decode (libpng), out="] = (
            imagecodecs.__version__, lambda path, dst: imagecodecs.png_decode(path.read_bytes(), out=dst))
        if pyspng is not None:
            def read_spng(path, dst):
                img = pyspng.load(path.read_bytes())
                dst[...] = img[..., 0] if img.ndim == 3 else img  # 0.1.4 returns G16 as grey+alpha
            out["pyspng.load (libspng)"] = (importlib.metadata.version("pyspng"), read_spng)
    elif ext == "tif":
        def read_tifffile(path, dst):
            with tifffile.TiffFile(path) as tif:
                tif.pages[0].asarray(out=dst, maxworkers=1)
        out["tifffile asarray, out="] = (tifffile.__version__, read_tifffile)
        def read_libtiff(path, dst):
            dst[...] = imagecodecs.tiff_decode(path.read_bytes())
        out["imagecodecs.tiff_decode (libtiff)"] = (imagecodecs.__version__, read_libtiff)
    elif ext == "bmp":
        out["imagecodecs.bmp_decode, out="] = (
            imagecodecs.__version__, lambda path, dst: imagecodecs.bmp_decode(path.read_bytes(), out=dst))
    return out


def timed(fn, repeats, before=None):
    """Median wall and CPU seconds (all threads) of ``repeats`` calls; ``before`` runs untimed."""
    walls, cpus = [], []
    for _ in range(repeats):
        if before is not None:
            before()
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    return statistics.median(walls), statistics.median(cpus), walls


def rate(px, wall, cpu):
    return {"median_s": round(wall, 3), "m_px_per_s": round(px / wall / 1e6, 1),
            "cpu_s": round(cpu, 3), "m_px_per_cpu_s": round(px / cpu / 1e6, 1)}


def read_stack(files, shape, dtype, reader, threads):
    """The harness every candidate runs in: one preallocated stack, one thread per core."""
    stack = np.empty((len(files), *shape), dtype)
    with ThreadPoolExecutor(max_workers=threads) as pool:
        list(pool.map(lambda i: reader(files[i], stack[i]), range(len(files))))
    return stack


def evict(files):
    for p in files:
        fd = os.open(p, os.O_RDONLY)
        try:
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)


def write_variant(folder, name, frames16, frames8):
    _, ext, bits, writer = VARIANTS[name]
    frames = frames8 if bits == 8 else frames16
    t0 = time.perf_counter()
    if writer == "write_frames":
        write_frames(folder, frames, SEQ, bit_depth=12 if bits == 16 else 8, fmt=ext)
    else:
        spec = {**SEQ.to_dict(), "width_px": frames.shape[2], "height_px": frames.shape[1],
                "bit_depth": 12 if bits == 16 else 8}
        (folder / "sequence.yaml").write_text(yaml.safe_dump(spec, sort_keys=False))
        with ThreadPoolExecutor(max_workers=len(os.sched_getaffinity(0))) as pool:
            list(pool.map(lambda i: writer(folder / SEQ.frame_name(*SEQ.frames()[i], ext=ext), frames[i]),
                          range(SEQ.n_frames)))
    files = sorted(folder.glob(f"*.{ext}"))
    for p in files:  # on disk, so that evicting them from the page cache makes a cold read
        with open(p, "rb+") as f:
            os.fsync(f.fileno())
    return time.perf_counter() - t0, files


def zlib_stream(path):
    """A PNG's IDAT payloads joined: its zlib stream."""
    buf = np.fromfile(path, np.uint8)
    z = np.empty_like(buf)
    zlen, _ = _png_gather_idat(buf, z)
    return z[:zlen].tobytes()


def png_filters(files):
    """Rows per PNG filter type over all files (what the writer chose)."""
    counts = np.zeros(5, np.int64)
    for p in files:
        head = np.fromfile(p, np.uint8, count=25)
        w, bits = int.from_bytes(head[16:20].tobytes(), "big"), int(head[24])
        rows = np.frombuffer(imagecodecs.zlib_decode(zlib_stream(p)), np.uint8)
        counts += np.bincount(rows[::w * bits // 8 + 1], minlength=5)[:5]
    return dict(zip(["none", "sub", "up", "average", "paeth"], counts.tolist(), strict=True))


def inflate_bound(files, shape, itemsize, threads, repeats, px):
    """The zlib streams in memory, inflated by libdeflate on ``threads`` threads into
    per-thread buffers; other inflaters on one thread over the first 10 streams."""
    streams = [zlib_stream(p) for p in files]
    n_raw = shape[0] * (shape[1] * itemsize + 1)
    local = threading.local()

    def inflate(z):
        if getattr(local, "buf", None) is None:
            local.buf = np.empty(n_raw, np.uint8)
        imagecodecs.deflate_decode(z, out=memoryview(local.buf))

    def run():
        with ThreadPoolExecutor(max_workers=threads) as pool:
            list(pool.map(inflate, streams))

    wall, cpu, _ = timed(run, repeats)
    out = {"libdeflate_on_all_threads": rate(px, wall, cpu),
           "compressed_mb": round(sum(map(len, streams)) / 2**20, 1)}
    one = {"libdeflate (imagecodecs.deflate_decode)": lambda z: imagecodecs.deflate_decode(z, out=n_raw),
           "zlib-ng (imagecodecs.zlibng_decode)": lambda z: imagecodecs.zlibng_decode(z, out=n_raw),
           "zlib 1.2.13 (imagecodecs.zlib_decode)": lambda z: imagecodecs.zlib_decode(z, out=n_raw)}
    isal = _optional("isal.isal_zlib")
    if isal is not None:
        one["ISA-L (isal.isal_zlib.decompress)"] = lambda z: isal.decompress(z, bufsize=n_raw)
    frame_px = px / len(files)
    single = {}
    for name, fn in one.items():
        t0, c0 = time.perf_counter(), time.thread_time()
        for z in streams[:10]:
            fn(z)
        wall, cpu = (time.perf_counter() - t0) / 10, (time.thread_time() - c0) / 10
        single[name] = {"ms_per_frame": round(1000 * wall, 2), "m_px_per_s_one_thread": round(frame_px / wall / 1e6, 1),
                        "m_px_per_cpu_s": round(frame_px / cpu / 1e6, 1)}
    out["one_thread"] = single
    return out


def peak_rss(folder, threads):
    """Peak RSS of a fresh process while it reads the folder once, against its RSS just
    before (fringecal imported, the numba kernels loaded; the peak reset there through
    /proc/self/clear_refs)."""
    code = (
        "import json, re, sys, numpy as np\n"
        "from fringecal.fringe import frame_files as f, importer as m\n"
        "for dt in (np.uint8, np.uint16):\n"
        "    m._frame_stats(np.zeros((1, 1, 1), dt), 1, 1); f._png_unfilter(np.zeros(3, np.uint8), np.zeros((1, 1), dt))\n"
        "f._png_gather_idat(np.zeros(8, np.uint8), np.zeros(8, np.uint8))\n"
        "def kib(key): return int(re.search(key + r':\\s+(\\d+)', open('/proc/self/status').read()).group(1))\n"
        "open('/proc/self/clear_refs', 'w').write('5')\n"
        "r0 = kib('VmRSS')\n"
        "s = m.read_frames(sys.argv[1], threads=int(sys.argv[2]))\n"
        "print(json.dumps([r0, kib('VmHWM'), s.frames.nbytes]))\n")
    root = str(Path(__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([root, os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run([sys.executable, "-c", code, str(folder), str(threads)], capture_output=True, text=True,
                         env=env, check=True)
    r0, r1, stack = json.loads(out.stdout)
    mb = 1 / 1024  # /proc/self/status counts KiB
    return {"stack_mb": round(stack / 2**20, 1), "rss_before_read_mb": round(r0 * mb, 1),
            "peak_rss_mb": round(r1 * mb, 1), "peak_increase_mb": round((r1 - r0) * mb, 1),
            "beyond_the_stack_mb": round((r1 - r0) * mb - stack / 2**20, 1)}


def bench_variant(folder, name, files, shape, dtype, threads, repeats, px, memory=True):
    desc, ext, _, _ = VARIANTS[name]
    load0 = os.getloadavg()
    size = sum(p.stat().st_size for p in files)
    res = {"what": desc, "files_mb": round(size / 2**20, 1),
           "compression_ratio": round(size / (px * np.dtype(dtype).itemsize), 3)}
    read_frames(folder, threads=threads)  # warm: page cache, numba cache
    wall, cpu, walls = timed(lambda: read_frames(folder, threads=threads), repeats)
    res["read_frames"] = {**rate(px, wall, cpu), "times_s": [round(t, 3) for t in walls]}
    if ext == "png":  # right after read_frames, in the same conditions
        bound = inflate_bound(files, shape, np.dtype(dtype).itemsize, threads, repeats, px)
        res["inflate_bound"] = bound
        res["read_frames_fraction_of_inflate_bound"] = {
            "wall": round(res["read_frames"]["m_px_per_s"] / bound["libdeflate_on_all_threads"]["m_px_per_s"], 2),
            "cpu": round(res["read_frames"]["m_px_per_cpu_s"] / bound["libdeflate_on_all_threads"]["m_px_per_cpu_s"],
                         2)}
        res["row_filters_chosen"] = png_filters(files)
    cw, cc, cwalls = timed(lambda: read_frames(folder, threads=threads), repeats, before=lambda: evict(files))
    res["read_frames_cold_cache"] = {**rate(px, cw, cc), "times_s": [round(t, 3) for t in cwalls]}
    bw, _, _ = timed(lambda: [p.read_bytes() for p in files], repeats, before=lambda: evict(files))
    res["cold_file_bytes_only"] = {"median_s": round(bw, 3), "mb_per_s": round(size / 2**20 / bw, 1)}
    res["memory"] = peak_rss(folder, threads) if memory else {"skipped": "--smoke: the first variant's only"}
    others = {}
    for cname, (version, reader) in candidates(ext).items():
        try:
            read_stack(files[:2], shape, dtype, reader, threads)
            w, c, _ = timed(lambda r=reader: read_stack(files, shape, dtype, r, threads), repeats)
            others[cname] = {"version": version, **rate(px, w, c)}
        except Exception as err:  # a library that cannot read this variant
            others[cname] = {"version": version, "fails": f"{type(err).__name__}: {str(err)[:120]}"}
    res["candidates_same_harness"] = others
    res["load_average_before_after"] = [round(load0[0], 2), round(os.getloadavg()[0], 2)]
    return res


def first_touch(shape, threads, repeats):
    """A fresh (98, H, W) uint16 stack written once by ``threads`` threads: the page
    faults (and zeroing) every import pays for its output, which the inflate bound does not."""
    def run():
        stack = np.empty((SEQ.n_frames, *shape), np.uint16)
        with ThreadPoolExecutor(max_workers=threads) as pool:
            list(pool.map(lambda i: stack[i].fill(1), range(SEQ.n_frames)))

    wall, cpu, walls = timed(run, repeats)
    return {"median_s": round(wall, 3), "cpu_s": round(cpu, 3), "times_s": [round(t, 3) for t in walls],
            "note": "varies with the kernel's supply of huge pages on this shared VM (numpy asks for them)"}


def overlap_probe(folder, frames16, threads, repeats):
    """read_frames of the vendor PNGs and decode() of a stack in memory: apart, and side
    by side (decode in a second thread while the files are read)."""
    full_scale = 4095
    decode(frames16[:, :16, :16].copy(), SEQ, full_scale=full_scale)
    r, _, _ = timed(lambda: read_frames(folder, threads=threads), repeats)
    d, _, _ = timed(lambda: decode(frames16, SEQ, full_scale=full_scale), repeats)

    def both():
        t = threading.Thread(target=decode, args=(frames16, SEQ), kwargs={"full_scale": full_scale})
        t.start()
        read_frames(folder, threads=threads)
        t.join()

    b, _, _ = timed(both, repeats)
    return {"read_frames_s": round(r, 3), "decode_s": round(d, 3), "one_after_the_other_s": round(r + d, 3),
            "side_by_side_s": round(b, 3), "most_streaming_could_save_s": round(r + d - b, 3),
            "note": "side by side = the most any overlap of reading and decoding could achieve; decode here "
                    "processes a whole stack, streaming would decode one orientation behind the reading"}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=2048)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)))
    p.add_argument("--variants", default=",".join(VARIANTS))
    p.add_argument("--no-overlap-probe", action="store_true")
    p.add_argument("--workdir", type=Path, help="write the variants here and keep them; a variant folder that "
                   "already holds its 98 files and sequence.yaml is reused (default: a temporary folder)")
    args = add_options(p).parse_args(argv)
    if args.smoke:
        args.size, args.repeats, args.variants = 64, 1, "png16_fringecal,tif_lzw"
    names = [v for v in args.variants.split(",") if v]
    unknown = set(names) - set(VARIANTS)
    if unknown:
        p.error(f"unknown variants {sorted(unknown)}; choose from {list(VARIANTS)}")
    head = conditions("image_import", argv, args.smoke)
    t0 = time.perf_counter()
    frames16, _, _ = make_frames(args.size)
    frames8 = (frames16 >> 4).astype(np.uint8)
    gen_s = time.perf_counter() - t0
    shape = (args.size, args.size)
    px = SEQ.n_frames * args.size * args.size
    root = args.workdir or Path(tempfile.mkdtemp(prefix="fringecal-import-"))
    doc = {**head,
           "machine": {"cpus": os.cpu_count(), "threads": args.threads, "numba_threads": nb.get_num_threads(),
                       "note": "shared 2-core machine; warm = files in the page cache (read once before timing); "
                               "M px/s counts frame pixels (98 x H x W per measurement); CPU s are all threads'"},
           "measurement": {"frames": SEQ.n_frames, "height_px": args.size, "width_px": args.size,
                           "mpx": round(px / 1e6, 1), "data": "12-bit fringes with 8 DN noise (benchmarks/decode.py)",
                           "generate_s": round(gen_s, 1)},
           "versions": {"imagecodecs": imagecodecs.__version__, "tifffile": tifffile.__version__,
                        "libdeflate": imagecodecs.deflate_version(), "libpng": imagecodecs.png_version()},
           "variants": {}}
    try:
        written = {}
        for name in names:
            folder = root / name
            files = sorted(folder.glob(f"*.{VARIANTS[name][1]}"))
            spec = yaml.safe_load((folder / "sequence.yaml").read_text()) if (folder / "sequence.yaml").exists() else {}
            if args.workdir and len(files) == SEQ.n_frames and spec.get("width_px") == args.size:
                written[name] = files
                print(f"reusing {folder}", file=sys.stderr)
                continue
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir(parents=True)
            write_s, files = write_variant(folder, name, frames16, frames8)
            written[name] = files
            print(f"wrote {name} in {write_s:.1f} s", file=sys.stderr)
        doc["fresh_stack_first_touch"] = first_touch(shape, args.threads, args.repeats)
        if not args.no_overlap_probe and "png16_vendor" in written:
            doc["overlap_probe"] = overlap_probe(root / "png16_vendor", frames16, args.threads, args.repeats)
        del frames16, frames8
        for name in names:
            dtype = np.uint8 if VARIANTS[name][2] == 8 else np.uint16
            doc["variants"][name] = bench_variant(root / name, name, written[name], shape, dtype, args.threads,
                                                  args.repeats, px, memory=not args.smoke or name == names[0])
            print(f"measured {name}", file=sys.stderr)
    finally:
        if args.workdir is None:
            shutil.rmtree(root, ignore_errors=True)
    return finish(doc, args.out)


if __name__ == "__main__":
    main()
