"""Resizing to the shard size: squash keeps the whole frame, center-crop its central square; a damaged clip's
fault is described the same however the decoder meets the damage."""

import struct
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from data_pipeline import decode
from data_pipeline.decode import ClipError, decode_clip, resize_frame
from data_pipeline.sample_data import write_webm
from fixtures.make_fixtures import gradient  # noqa: I001 (tests/data_pipeline/fixtures)


def test_squash_and_center_crop():
    frame = np.zeros((240, 400, 3), np.uint8)
    frame[:, :80] = 255  # a white band on the left fifth
    squashed = resize_frame(frame, 64, "squash")
    cropped = resize_frame(frame, 64, "center-crop")
    assert squashed.shape == cropped.shape == (64, 64, 3)
    assert squashed[:, :12].min() == 255 and squashed[:, 14:].max() == 0  # the band survives, squeezed
    assert cropped.max() == 0  # the crop (columns 80..319) leaves it out
    np.testing.assert_array_equal(cropped, cv2.resize(frame[:, 80:320], (64, 64), interpolation=cv2.INTER_AREA))
    with pytest.raises(ValueError, match="squash, center-crop"):
        resize_frame(frame, 64, "stretch")


def test_a_damaged_clip_is_described_the_same_whether_the_decoder_stops_or_raises(tmp_path, monkeypatch):
    """decord stops at a damaged packet on one run and fails a check there on another; errors.jsonl must say the
    same either way (a resumed build is byte-identical to an unbroken one)."""
    path = tmp_path / "clip.webm"
    write_webm(path, np.random.default_rng(0).integers(0, 256, (36, 64, 96, 3), dtype=np.uint8))
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])  # truncated, as sample-data's broken clips
    with pytest.raises(ClipError) as stopped:
        decode_clip(path, 64)
    assert stopped.value.reason == "corrupt" and "fewer frames decode than the" in stopped.value.detail
    stopping = decode._decode_decord

    def raising(clip_path):  # after fewer frames, as decord may
        frames = stopping(clip_path)
        yield next(frames)
        yield next(frames)
        raise RuntimeError("Check failed: avcodec_send_packet(dec_ctx_.get(), pkt.get()) >= 0")

    monkeypatch.setattr(decode, "_decode_decord", raising)
    with pytest.raises(ClipError) as raised:
        decode_clip(path, 64)
    assert (raised.value.reason, raised.value.detail) == (stopped.value.reason, stopped.value.detail)


def test_a_decoder_error_without_a_message_is_a_clip_error_not_a_crash(tmp_path, monkeypatch):
    path = tmp_path / "clip.webm"
    write_webm(path, np.random.default_rng(0).integers(0, 256, (12, 64, 96, 3), dtype=np.uint8))
    whole = decode._decode_decord

    def raising_bare(clip_path):  # a whole stream, then an error with no message
        yield from whole(clip_path)
        raise RuntimeError()

    monkeypatch.setattr(decode, "_decode_decord", raising_bare)
    with pytest.raises(ClipError) as raised:  # an IndexError killed the decoder process: recorded as "crashed"
        decode_clip(path, 64)
    assert (raised.value.reason, raised.value.detail) == ("corrupt", "decord: RuntimeError")


def test_a_path_that_holds_no_video_file_says_what_is_there(tmp_path):
    """A directory or a device at <id>.webm was reported as "no file at" it."""
    (tmp_path / "dir.webm").mkdir()
    (tmp_path / "device.webm").symlink_to("/dev/null")
    for name, detail in (("nothing.webm", "no file at "), ("dir.webm", "dir.webm is a directory, not a video file"),
                         ("device.webm", "device.webm is not a regular file, not a video file")):
        with pytest.raises(ClipError) as error:
            decode_clip(tmp_path / name, size=64)
        assert error.value.reason == "missing" and detail in error.value.detail, name


@pytest.mark.parametrize("height, width", [(24, 24), (24, 48), (16, 16), (40, 2)])
def test_narrow_videos_that_decord_mis_shapes_decode_as_opencv_reads_them(tmp_path, height, width):
    """decord 0.6 gives [H, W, 4] or [H, W, 6] frames of shifted rows for some widths (16, 24, 48, 72 px, and a
    2 px one [H, W, 48]): 4-channel ones went into the shards as JPEGs of garbage colours, the rest made the
    decoder process crash (recorded as `crashed`, retried by every --retry-failed)."""
    path = tmp_path / "narrow.webm"
    frames = np.random.default_rng(0).integers(0, 256, (6, height, width, 3), dtype=np.uint8)
    write_webm(path, frames)
    clip = decode_clip(path, 64)
    capture = cv2.VideoCapture(str(path))
    expected = []
    while (read := capture.read())[0]:
        expected.append(resize_frame(read[1][:, :, ::-1], 64, "squash"))
    assert clip.frames.shape == (6, 64, 64, 3) and (clip.source_height, clip.source_width) == (height, width)
    np.testing.assert_array_equal(clip.frames, np.stack(expected))


def test_a_video_of_odd_height_is_decoded_by_opencv_with_its_colours_in_place(tmp_path):
    """decord 0.6 decodes VP9 4:2:0 of odd height with the colour rows misplaced (2.1 grey levels from the source
    here, up to 11 at other heights), silently; OpenCV gets them right."""
    path = Path(__file__).parent / "fixtures" / "vp9_64x41.webm"  # fixtures/make_fixtures.py: OpenCV cannot write it
    clip = decode_clip(path, 64)
    assert clip.decoder == "opencv" and (clip.source_height, clip.source_width) == (41, 64)
    source = resize_frame(gradient(41, 64), 64, "squash").astype(int)
    assert np.abs(clip.frames.astype(int) - source).mean() < 1.2  # the encoding's own loss: about 0.9


def test_a_container_declaring_an_absurd_duration_is_corrupt_not_a_crashed_decoder(tmp_path):
    """A damaged Matroska Duration of 1e15 ms made decord abort the whole process (std::bad_alloc): the build
    recorded the clip as `crashed`, which every --retry-failed tried again, and crashed again."""
    path = tmp_path / "clip.webm"
    write_webm(path, np.zeros((24, 64, 96, 3), np.uint8))
    data = bytearray(path.read_bytes())
    duration = data.find(b"\x44\x89\x88")  # the Segment's Duration element: an 8-byte float, in ms
    data[duration + 3:duration + 11] = struct.pack(">d", 1e15)
    path.write_bytes(bytes(data))
    decoded = subprocess.run([sys.executable, "-c", "import sys; from data_pipeline.decode import decode_clip; "
                              "decode_clip(sys.argv[1], 64)", str(path)], capture_output=True, text=True,
                             cwd=Path(__file__).parents[2])
    assert decoded.returncode == 1 and "ClipError: corrupt: the stream breaks off" in decoded.stderr, decoded.stderr


def test_a_video_that_cannot_be_read_is_unreadable_not_undecodable(tmp_path, monkeypatch):
    """A file without read permission (or an I/O error of network storage) was `undecodable`, a fact of the file that
    --retry-failed never retries: once readable, the clip stayed out of the shards for good."""
    path = tmp_path / "clip.webm"
    write_webm(path, np.zeros((12, 64, 96, 3), np.uint8))
    real_open = open

    def denied(file, *args, **kwargs):
        if str(file) == str(path):
            raise PermissionError(13, "Permission denied", str(file))
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr("builtins.open", denied)
    with pytest.raises(ClipError, match=rf"^unreadable: {path}: Permission denied$"):
        decode_clip(path, 64)


@pytest.mark.parametrize("seed", [1, 2, 3, 8])
def test_a_stream_with_a_hole_in_the_middle_is_corrupt(tmp_path, seed):
    """The sample data's `corrupt` clips of these seeds decode with a hole of 11-19 frames in the middle (and a garbage
    frame before it) and end on time: timed by their last frame alone, they went into the shards as good clips."""
    from data_pipeline.sample_data import make_sample_data

    broken = make_sample_data(tmp_path, clips=3, with_broken=True, seed=seed)
    corrupt = next(clip for clip, kind in broken.items() if kind == "corrupt")
    with pytest.raises(ClipError, match="^corrupt: the stream has a hole"):
        decode_clip(next((tmp_path / "videos").glob(f"{corrupt}.*")), 64)


@pytest.mark.parametrize("decoder", ["decord", "opencv"])
def test_a_video_whose_timestamps_skip_frames_is_whole_not_corrupt(monkeypatch, decoder):
    """A camera that drops frames writes 30 frames over 3 s at 12 fps: its container declares 36. Counting frames
    against that, the build recorded every such clip as `corrupt` (never retried) though each frame decodes."""
    def cannot_open(path):  # as decord does with files it cannot read
        raise RuntimeError("cannot open")
        yield

    if decoder == "opencv":
        monkeypatch.setattr(decode, "_decode_decord", cannot_open)
    clip = decode_clip(Path(__file__).parent / "fixtures" / "vp9_dropped_frames.webm", 64)
    assert clip.decoder == decoder and clip.frames.shape == (30, 64, 64, 3)
    np.testing.assert_allclose(clip.frames.mean((1, 2, 3)), 8 * np.arange(30), atol=3)  # every frame, in order
