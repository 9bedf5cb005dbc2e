"""Resizing to the shard size: squash keeps the whole frame, center-crop its central square."""

import cv2
import numpy as np
import pytest

from data_pipeline.decode import resize_frame


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
