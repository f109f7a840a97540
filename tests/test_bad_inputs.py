"""The bad inputs that once gave a traceback, a wrong message, a hang or gigabytes of memory to ``eonav locate`` and
``eonav fuse``, generated from a table: each gives ``eonav CMD: error: ...`` naming the problem, exit 2, no
traceback, in under 2 s of CPU and under a 1 GiB address-space limit (the CLI runs as a real process with
``RLIMIT_AS`` set). The decompression bomb is a real PNG of 32000 x 32000 pixels that OpenCV decodes (checked
on a smaller one made the same way)."""
import json
import os
import resource
import struct
import subprocess
import sys
import time
import zlib

import cv2
import numpy as np
import pytest

AS_LIMIT = 1 << 30
W, H = 32, 24
CAM = {"width": W, "height": H, "fx": 40.0, "fy": 40.0, "cx": 15.5, "cy": 11.5}


def pair_doc(img0="f0.png", img1="f1.png"):
    return {"cameras": {"nose": dict(CAM)},
            "frames": [{"image": img0, "camera": "nose", "t": 0.0, "position_ned_m": [0, 0, -5], "ypr_deg": [0, 0, 0]},
                       {"image": img1, "camera": "nose", "t": 0.1, "position_ned_m": [1, 0, -5], "ypr_deg": [0, 0, 0]}]}


def png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def zero_png(w: int, h: int, rows_per_block: int = 500) -> bytes:
    """A valid 8-bit grey PNG of w x h black pixels. Its zlib stream is one block of ``rows_per_block`` rows
    compressed with a full flush (no back-reference across it) repeated, then the rest: seconds of compression
    saved. The Adler-32 of n zero bytes is (n mod 65521) << 16 | 1."""
    row = bytes(w + 1)                                    # filter byte 0 + w zero pixels

    def deflate(n_rows):                                  # non-final deflate blocks of n_rows rows
        c = zlib.compressobj(9)
        return (c.compress(row * n_rows) + c.flush(zlib.Z_FULL_FLUSH))[2:]     # without the zlib header

    n, rest = divmod(h, rows_per_block)
    body = deflate(rows_per_block) * n + (deflate(rest) if rest else b"")
    adler = ((h * (w + 1)) % 65521) << 16 | 1
    stream = b"\x78\xda" + body + b"\x03\x00" + struct.pack(">I", adler)    # + an empty final block
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", ihdr) + png_chunk(b"IDAT", stream) + png_chunk(b"IEND", b"")


def header_only_png(w: int, h: int) -> bytes:
    """A PNG whose header claims w x h with a few bytes of image data."""
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", ihdr) + png_chunk(b"IDAT", zlib.compress(bytes(1000)))
            + png_chunk(b"IEND", b""))


def test_the_bomb_generator_makes_a_png_that_opencv_decodes():
    img = cv2.imdecode(np.frombuffer(zero_png(700, 1234), np.uint8), cv2.IMREAD_UNCHANGED)
    assert img is not None and img.shape == (1234, 700) and not img.any()
    img = cv2.imdecode(np.frombuffer(zero_png(64, 1000), np.uint8), cv2.IMREAD_UNCHANGED)   # no remainder block
    assert img is not None and img.shape == (1000, 64)


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    d = tmp_path_factory.mktemp("bad")
    rng = np.random.default_rng(3)
    for name in ("f0.png", "f1.png"):
        cv2.imwrite(str(d / name), rng.integers(0, 255, (H, W), dtype=np.uint8))
    (d / "good.json").write_text(json.dumps(pair_doc()))
    (d / "bomb.png").write_bytes(zero_png(32000, 32000))
    (d / "huge_header.png").write_bytes(header_only_png(100000, 100000))
    (d / "adir").mkdir()
    os.mkfifo(d / "fifo")
    os.symlink("/dev/zero", d / "zero")
    for name, img in (("bomb", "bomb.png"), ("huge_header", "huge_header.png"), ("img_dir", "adir"),
                      ("img_fifo", "fifo"), ("img_zero", "zero")):
        (d / f"{name}.json").write_text(json.dumps(pair_doc(img1=img)))
    (d / "latin1.json").write_bytes(json.dumps(pair_doc(), ensure_ascii=False).replace("nose", "caméra")
                                    .encode("latin-1"))
    np.savez(d / "small_truth.npz", range_m=np.full((10, 10), 5.0, np.float32))     # not the camera's 32 x 24
    (d / "nested.json").write_text("[" * 100_000)
    (d / "digits.json").write_text('{"cameras": ' + "7" * 5000 + "}")
    with open(d / "big.json", "wb") as f:                  # 17 MiB, sparse: the size alone refuses it
        f.truncate(17 << 20)
    return d


# name -> (command, arguments relative to the work folder, the error it must give)
CASES = {
    "not_utf8": ("locate", ["latin1.json"], r"pair file .*latin1.json: not UTF-8 text \(byte 0xe9 at offset \d+\)"),
    "nested": ("locate", ["nested.json"], r"not valid JSON \(nested too deeply\)"),
    "digits": ("locate", ["digits.json"], r"not valid JSON \(.*digits"),
    "huge_header": ("locate", ["huge_header.json"],
                    r"frames\[1\].image huge_header.png: image is 100000x100000 but camera 'nose' declares 32x24"),
    "bomb": ("locate", ["bomb.json"], r"frames\[1\].image bomb.png: image is 32000x32000 but camera 'nose' declares"),
    "out_proc": ("locate", ["good.json", "--out", "/proc/eonav-none/range.npz"], r"--out /proc/eonav-none/range.npz: "
                 r"cannot create a file in /proc/eonav-none"),
    "out_proc_top": ("locate", ["good.json", "--out", "/proc/range.npz"], r"cannot create a file in /proc "),
    "out_dir": ("locate", ["good.json", "--out", "adir"], r"--out .*adir: is a directory, expected a file name"),
    "out_fifo": ("locate", ["good.json", "--out", "fifo"], r"--out .*fifo: is a FIFO \(named pipe\)"),
    "png_no_writer": ("locate", ["good.json", "--png", "range.nopicture"], r"--png .*: no image writer"),
    "truth_not_npz": ("locate", ["good.json", "--truth", "good.json"], r"--truth .*good.json: not an .npz file"),
    "truth_shape": ("locate", ["good.json", "--truth", "small_truth.npz"],
                    r"--truth .*small_truth.npz: shape \(10, 10\) differs from the range map \(24, 32\)"),
    "other_zero": ("locate", ["good.json", "--other", "0"], r"--other 0: the pair file has frames 0\.\.1"),
    "pair_dir": ("locate", ["adir"], r"pair file .*adir: is a directory, expected a regular file"),
    "pair_fifo": ("locate", ["fifo"], r"pair file .*fifo: is a FIFO \(named pipe\), expected a regular file"),
    "pair_dev_zero": ("locate", ["/dev/zero"], r"pair file /dev/zero: is a character device, expected a regular"),
    "pair_too_big": ("locate", ["big.json"], r"pair file .*big.json: 17825792 bytes, more than the 16777216"),
    "pair_missing": ("locate", ["none.json"], r"pair file not found: .*none.json"),
    "img_dir": ("locate", ["img_dir.json"], r"image file .*adir: is a directory, expected a regular file"),
    "img_fifo": ("locate", ["img_fifo.json"], r"image file .*fifo: is a FIFO"),
    "img_dev_zero": ("locate", ["img_zero.json"], r"image file .*zero: is a character device"),
    "fuse_not_utf8": ("fuse", ["latin1.json"], r"sequence file .*latin1.json: not UTF-8 text"),
    "fuse_nested": ("fuse", ["nested.json"], r"sequence file .*: not valid JSON \(nested too deeply\)"),
    "fuse_fifo": ("fuse", ["fifo"], r"sequence file .*fifo: is a FIFO"),
    "fuse_dev_zero": ("fuse", ["/dev/zero"], r"sequence file /dev/zero: is a character device"),
    "fuse_bomb": ("fuse", ["bomb.json"], r"frames\[1\].image bomb.png: image is 32000x32000"),
    "fuse_out_dir": ("fuse", ["good.json", "--out", "adir"], r"--out .*adir: is a directory"),
    "fuse_out_dir_is_file": ("fuse", ["good.json", "--out-dir", "good.json"], r"--out-dir .*: exists and is not a dir"),
}


def limit_memory():
    resource.setrlimit(resource.RLIMIT_AS, (AS_LIMIT, AS_LIMIT))


def run_limited(args, cwd):
    """The CLI as a real process under RLIMIT_AS; returns (result, CPU seconds of the child, wall seconds)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "eonav.app.cli", *args], cwd=cwd, capture_output=True, text=True,
                       timeout=60, preexec_fn=limit_memory, stdin=subprocess.DEVNULL)
    wall = time.monotonic() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return r, cpu, wall


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_input_gives_a_clear_error_quickly(work, case):
    import re
    cmd, args, match = CASES[case]
    if "--out" not in args:
        args = [*args, "--out", str(work / f"out_{case}.npz")]
    r, cpu, wall = run_limited([cmd, *args], work)
    assert r.returncode == 2, f"{case}: exit {r.returncode}\n{r.stderr[-2000:]}"
    assert "Traceback" not in r.stderr, r.stderr[-2000:]
    line = r.stderr.strip().splitlines()[-1]
    assert line.startswith(f"eonav {cmd}: error: "), line
    assert re.search(match, line), f"{case}: {line!r} does not match {match!r}"
    assert cpu < 2.0, f"{case}: {cpu:.2f} s of CPU"
    assert wall < 20.0, f"{case}: {wall:.1f} s"           # never blocks (a FIFO with no writer)
    assert not (work / f"out_{case}.npz").exists()         # refused before writing anything


def test_the_good_pair_runs_under_the_same_limit(work, tmp_path):
    """The limit and the folder are not what makes the cases fail: the good pair file ranges there."""
    r, cpu, wall = run_limited(["locate", "good.json", "--out", str(tmp_path / "r.npz"), "--method", "paper"], work)
    assert r.returncode == 0, r.stderr[-2000:]
    with np.load(tmp_path / "r.npz") as z:
        assert z["range_m"].shape == (H, W)
