"""Input files are read safely (eonav.io.files, eonav.io.images, eonav.io.pairfile): the size an image declares is
read from its header and checked before decoding, every byte and pixel limit holds on both sides, and outputs are
written under exactly the name given."""
import copy
import json

import cv2
import numpy as np
import pytest

from eonav import InputError
from eonav.io import files, images, pairfile


@pytest.mark.parametrize("ext,shape,dtype,params", [
    (".png", (37, 53), np.uint8, []), (".png", (19, 7, 3), np.uint16, []), (".png", (5, 300, 4), np.uint8, []),
    (".jpg", (41, 29), np.uint8, []), (".jpg", (33, 65, 3), np.uint8, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1]),
    (".tif", (23, 31), np.uint16, []), (".tif", (17, 9, 3), np.uint8, []),
])
def test_header_size_is_the_written_size(tmp_path, ext, shape, dtype, params):
    a = np.random.default_rng(2).integers(0, np.iinfo(dtype).max, shape, dtype=dtype)
    p = tmp_path / f"x{ext}"
    assert cv2.imwrite(str(p), a, params)
    assert images.image_size(p.read_bytes()) == (shape[1], shape[0])
    assert images.load_grey(p, expect_wh=(shape[1], shape[0])).shape == shape[:2]


def test_size_mismatch_is_found_in_the_header_before_decoding(tmp_path, monkeypatch):
    p = tmp_path / "x.png"
    cv2.imwrite(str(p), np.zeros((24, 32), np.uint8))

    def no_decode(*a):
        raise AssertionError("decoded")
    monkeypatch.setattr(images.cv2, "imdecode", no_decode)
    with pytest.raises(images.ImageSizeError, match="is 32x24, expected 33x24") as e:
        images.load_grey(p, expect_wh=(33, 24))
    assert e.value.size == (32, 24)
    with pytest.raises(images.ImageSizeError, match="more than the 767 eonav decodes"):
        images.load_grey(p, max_pixels=32 * 24 - 1)
    with pytest.raises(AssertionError, match="decoded"):         # the right size goes on to the decoder
        images.load_grey(p, expect_wh=(32, 24), max_pixels=32 * 24)


def test_formats_without_a_header_reader_are_checked_after_decoding(tmp_path):
    p = tmp_path / "x.bmp"
    cv2.imwrite(str(p), np.zeros((24, 32, 3), np.uint8))
    assert images.image_size(p.read_bytes()) is None
    assert images.load_grey(p, expect_wh=(32, 24)).shape == (24, 32)
    with pytest.raises(images.ImageSizeError) as e:
        images.load_grey(p, expect_wh=(24, 32))
    assert e.value.size == (32, 24)


def test_file_size_bound_both_sides(tmp_path):
    p = tmp_path / "x.png"
    cv2.imwrite(str(p), np.zeros((24, 32), np.uint8))
    cap = images.RAW_BYTES_PER_PIXEL * 32 * 24 + images.FILE_SLACK_BYTES
    data = p.read_bytes()
    p.write_bytes(data + bytes(cap - len(data)))              # data after IEND is ignored by the decoder
    assert images.load_grey(p, expect_wh=(32, 24)).shape == (24, 32)
    p.write_bytes(data + bytes(cap + 1 - len(data)))
    with pytest.raises(InputError, match=f"{cap + 1} bytes, more than the {cap} bytes allowed"):
        images.load_grey(p, expect_wh=(32, 24))


@pytest.mark.parametrize("data,match", [
    (b"\x89PNG\r\n\x1a\n\x00\x00\x00\x0dIHDX" + bytes(17), "PNG without an IHDR header"),
    (b"\x89PNG\r\n\x1a\n", "PNG without an IHDR header"),
    (b"\xff\xd8\xff\xe0\x00\x01", "JPEG segment of length 1"),
    (b"\xff\xd8\xff\xe0\x00\x04ab\x00\x00\x00\x00", "JPEG segment without a marker"),
    (b"\xff\xd8\xff\xda\x00\x04", "JPEG without a frame header"),
    (b"II*\x00\xff\xff\x00\x00", "TIFF first directory at byte 65535"),
    (b"MM\x00*\x00\x00\x00\x08\x00\x00", "TIFF without ImageWidth"),
])
def test_malformed_headers_are_input_errors(tmp_path, data, match):
    p = tmp_path / "x.img"
    p.write_bytes(data)
    with pytest.raises(InputError, match=f"cannot decode image .*{match}"):
        images.load_grey(p)


def test_read_regular_file_bound_both_sides(tmp_path):
    p = tmp_path / "f"
    p.write_bytes(b"x" * 100)
    assert files.read_regular_file(p, "thing", 100) == b"x" * 100
    with pytest.raises(InputError, match="thing .*: 100 bytes, more than the 99 bytes allowed"):
        files.read_regular_file(p, "thing", 99)


def test_outputs_are_checked_and_written_under_the_name_given(tmp_path):
    out = files.write_npz(tmp_path / "sub" / "range", {"a": np.arange(3)})
    assert out == tmp_path / "sub" / "range" and out.is_file()        # no .npz appended, folder made
    with np.load(out) as z:
        assert z["a"].tolist() == [0, 1, 2]
    with pytest.raises(InputError, match="is a directory"):
        files.check_output(tmp_path / "sub")
    ro = tmp_path / "ro.npz"
    ro.write_bytes(b"")
    ro.chmod(0o444)
    if not __import__("os").access(ro, __import__("os").W_OK):     # (root may write anyway)
        with pytest.raises(InputError, match="exists and is not writable"):
            files.check_output(ro)
    assert files.check_output("/dev/null") == __import__("pathlib").Path("/dev/null")


DOC = {"cameras": {"nose": {"width": 32, "height": 24, "fx": 40.0, "fy": 40.0, "cx": 15.5, "cy": 11.5}},
       "frames": [{"image": f"f{i}.png", "camera": "nose", "t": 0.1 * i, "position_ned_m": [i, 0, -5],
                   "ypr_deg": [0, 0, 0]} for i in range(3)]}


def test_pair_file_pixel_budget_both_sides_and_only_the_frames_asked_for(tmp_path, monkeypatch):
    for i in range(2):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), np.zeros((24, 32), np.uint8))     # f2.png does not exist
    p = tmp_path / "pair.json"
    p.write_text(json.dumps(DOC))
    pf = pairfile.load_pair_file(p)
    monkeypatch.setattr(pairfile, "MAX_TOTAL_PIXELS", 2 * 32 * 24)
    assert [v.image.shape for v in pf.views(indices=(0, 1))] == [(24, 32)] * 2
    with pytest.raises(InputError, match="3 images of 2304 pixels in all, more than the 1536"):
        pf.views()
    monkeypatch.setattr(pairfile, "MAX_TOTAL_PIXELS", 2 * 32 * 24 - 1)
    with pytest.raises(InputError, match="2 images of 1536 pixels in all"):
        pf.views(indices=(0, 1))


def test_pair_file_encodings(tmp_path):
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), np.zeros((24, 32), np.uint8))
    p = tmp_path / "pair.json"
    doc = copy.deepcopy(DOC)
    doc["cameras"] = {"caméra": doc["cameras"]["nose"]}
    for fr in doc["frames"]:
        fr["camera"] = "caméra"
    for enc in ("utf-8", "utf-8-sig", "utf-16", "utf-32"):     # the encodings JSON allows
        p.write_bytes(json.dumps(doc, ensure_ascii=False).encode(enc))
        assert list(pairfile.load_pair_file(p).cameras) == ["caméra"]
    p.write_bytes(json.dumps(doc, ensure_ascii=False).encode("latin-1"))
    with pytest.raises(InputError, match=r"not UTF-8 text \(byte 0xe9 at offset 17\)"):
        pairfile.load_pair_file(p)


def test_colour_is_read_in_opencv_channel_order_with_the_bt601_weights(tmp_path):
    """A colour file is B, G, R(, A) as OpenCV decodes it; grey = 0.114 B + 0.587 G + 0.299 R (ITU-R BT.601), alpha
    ignored. Pure blue, green, red on 255 -> 29.07, 149.685, 76.245 by hand. Catches reading the channels as RGB
    (blue would come out 76.245)."""
    want = np.array([[0.114 * 255, 0.587 * 255, 0.299 * 255]], np.float32)
    bgr = np.zeros((1, 3, 3), np.uint8)
    for k in range(3):
        bgr[0, k, k] = 255                                      # column k: channel k only (B, G, R)
    bgra = np.concatenate([bgr, np.full((1, 3, 1), 77, np.uint8)], axis=2)
    for name, img in (("bgr.png", bgr), ("bgra.png", bgra)):
        assert cv2.imwrite(str(tmp_path / name), img)
        np.testing.assert_allclose(images.load_grey(tmp_path / name, expect_wh=(3, 1)), want, atol=1e-3, err_msg=name)


def test_16_bit_files_come_out_on_the_8_bit_scale(tmp_path):
    """16-bit grey and colour (docs/pair-file.md: 8 or 16 bit) land on the 0..255 scale the ranging's thresholds
    assume: v / 257, so 65535 -> 255 and 257 k -> k exactly. Colour (B, G, R) = 257 (10, 20, 30) -> 0.114*10 +
    0.587*20 + 0.299*30 = 21.85 by hand, with or without alpha. Catches a dropped or wrong 16-bit scale."""
    grey = (257 * np.array([[0, 1, 100, 255]])).astype(np.uint16)
    assert cv2.imwrite(str(tmp_path / "g16.png"), grey)
    np.testing.assert_allclose(images.load_grey(tmp_path / "g16.png"), [[0, 1, 100, 255]], atol=1e-4)
    bgr = np.tile((257 * np.array([10, 20, 30])).astype(np.uint16), (2, 2, 1))
    bgra = np.concatenate([bgr, np.full((2, 2, 1), 65535, np.uint16)], axis=2)
    for name, img in (("c16.png", bgr), ("ca16.png", bgra)):
        assert cv2.imwrite(str(tmp_path / name), img)
        got = images.load_grey(tmp_path / name)
        assert got.dtype == np.float32
        np.testing.assert_allclose(got, np.full((2, 2), 21.85), atol=1e-3, err_msg=name)


def _jpeg_segments(data: bytes):
    """(marker, whole segment bytes) of a JPEG from after SOI up to start of scan, and the rest from SOS on."""
    i, segs = 2, []
    while data[i + 1] != 0xDA:
        n = 2 + int.from_bytes(data[i + 2:i + 4], "big")
        segs.append((data[i + 1], data[i:i + n]))
        i += n
    return segs, data[i:]


def test_jpeg_huffman_tables_before_the_frame_header(tmp_path):
    """JPEG allows its tables (DHT 0xC4, DQT) anywhere before the scan; some encoders write the Huffman tables before
    the frame header (SOF0 0xC0). The same 41 x 29 picture with its DHTs moved ahead of SOF0 decodes to the same
    pixels, and the header reader finds 41 x 29 in SOF0, not in a DHT (0xC4 is in the SOFn range 0xC0-0xCF but is
    not a frame header). Catches 0xC4 dropped from the SOFn exclusions (a table's bytes read as a size)."""
    a = np.random.default_rng(4).integers(0, 255, (29, 41), np.uint8)
    ok, buf = cv2.imencode(".jpg", a)
    assert ok
    segs, scan = _jpeg_segments(buf.tobytes())
    dht = [s for m, s in segs if m == 0xC4]
    assert dht and [m for m, _ in segs].index(0xC0) < [m for m, _ in segs].index(0xC4)   # OpenCV: SOF0 first
    moved = b"\xff\xd8" + b"".join(dht) + b"".join(s for m, s in segs if m != 0xC4) + scan
    p = tmp_path / "dht_first.jpg"
    p.write_bytes(moved)
    assert images.image_size(moved) == (41, 29)
    np.testing.assert_array_equal(images.load_grey(p, expect_wh=(41, 29)),
                                  cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE).astype(np.float32))
