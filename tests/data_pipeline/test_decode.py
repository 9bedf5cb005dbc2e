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
