"""scripts/view-judges.py: its extra views are the served preparation, zoomed and cropped, and
their intrinsics follow the pixels (issue 29's test-time-augmentation measurement)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from cmr.data import find_sequences, list_frames, make_sample

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "view-judges.py"


def load_script():
    spec = importlib.util.spec_from_file_location("view_judges", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_an_unzoomed_centre_view_is_the_served_sample(tiny_dataset):
    vj = load_script()
    frame = list_frames(find_sequences(tiny_dataset))[0]
    served = make_sample(frame, np.random.default_rng(0), train=False)
    [(image, k)] = vj.zoomed_views(frame, [(1.0, "c")])
    np.testing.assert_array_equal(image, served.image)
    np.testing.assert_allclose(k, served.intrinsics)


def test_a_zoomed_view_scales_the_focal_length_and_keeps_the_pixels_it_names(tiny_dataset):
    vj = load_script()
    frame = list_frames(find_sequences(tiny_dataset))[0]
    (base, k0), (left, kl), (centre, kc) = vj.zoomed_views(frame, [(1.0, "c"), (1.5, "l"), (1.5, "c")])
    assert kc[0] == pytest.approx(1.5 * k0[0], rel=0.01) and kl[1] == pytest.approx(1.5 * k0[1], rel=0.01)
    # the left crop starts at the zoomed image's edge: its principal point lies further right
    assert kl[2] > kc[2]
    # a ray through the served view's principal point lands on the zoomed views' principal points,
    # and the grey level there is the same scene (bilinear resampling, so within a few levels)
    grey = lambda img, u, v: img[:, int(round(v)), int(round(u))].mean()  # noqa: E731
    # (a 15-pixel error in cx makes it 1.2-2 on this data)
    for image, k in ((centre, kc), (left, kl)):
        assert abs(grey(image, k[2], k[3]) - grey(base, k0[2], k0[3])) < 0.35
    assert vj.parse_views("1.5:l,1.3:c") == [(1.5, "l"), (1.3, "c")]
    for bad in ("1.5:x", "0.5:c", "1.5"):
        with pytest.raises((SystemExit, ValueError)):
            vj.parse_views(bad)
