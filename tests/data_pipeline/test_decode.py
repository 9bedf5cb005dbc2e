"""Resizing to the shard size: squash keeps the whole frame, center-crop its central square; a damaged clip's
fault is described the same however the decoder meets the damage."""

import cv2
import numpy as np
import pytest

from data_pipeline import decode
from data_pipeline.decode import ClipError, decode_clip, resize_frame
from data_pipeline.sample_data import write_webm


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
