"""cmr.rescale: a resized copy of a sequence projects every point where the resize moved its pixel."""

import numpy as np
from PIL import Image

from cmr.rescale import main


def test_a_rescaled_sequence_projects_points_onto_the_resized_pixels(tmp_path):
    src = tmp_path / "src" / "000"
    (src / "image_2").mkdir(parents=True)
    (src / "velodyne").mkdir()
    Image.new("RGB", (100, 40), (10, 20, 30)).save(src / "image_2" / "000000.png")
    p2 = np.array([[700.0, 0, 48.3, 45.0], [0, 710.0, 19.6, -0.3], [0, 0, 1, 0.004]])
    calib = "\n".join(f"P{i}: " + " ".join(f"{v:.12e}" for v in p2.ravel()) for i in range(4))
    (src / "calib.txt").write_text(calib + "\nTr: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    (src / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    main([str(tmp_path / "src"), str(tmp_path / "dst"), "--factor", "2.5"])
    dst = tmp_path / "dst" / "000"
    assert Image.open(dst / "image_2" / "000000.png").size == (250, 100)
    rows = {l.split(":")[0]: l.split(":")[1] for l in (dst / "calib.txt").read_text().splitlines()}
    q2 = np.array(rows["P2"].split(), dtype=float).reshape(3, 4)
    assert rows["Tr"].split() == "1 0 0 0 0 1 0 0 0 0 1 0".split()
    assert (dst / "poses.txt").is_symlink()
    x = np.array([1.3, -0.7, 11.0, 1.0])
    u, v = (p2 @ x)[:2] / (p2 @ x)[2]
    u2, v2 = (q2 @ x)[:2] / (q2 @ x)[2]
    assert np.allclose([u2, v2], [(u + 0.5) * 2.5 - 0.5, (v + 0.5) * 2.5 - 0.5], atol=1e-9)
