"""`nerfjit.bake` and `nerfjit.Bake`: a trained field baked into splats from Python, their arrays, and their
views drawn by nerfjit's splat renderer into numpy images."""

import numpy as np
import pytest

import nerfjit
from conftest import trainer


def psnr(a, b):
    return -10 * np.log10(np.mean((np.asarray(a, np.float64) - b) ** 2))


def test_a_trained_box_bakes_into_splats_that_draw_its_views(box_views):
    nerfjit.run(str(trainer(box_views, steps=300)), out=box_views)
    checkpoint = box_views / "train.ckpt.safetensors"
    views = nerfjit.data.load(box_views / "cams.json")

    def drawn(scene, i):
        fx, fy, cx, cy = views["intrinsics"][i]
        return scene.render(views["c2w"][i], (fx, fy), 40, principal=(cx, cy))

    baked, report = nerfjit.bake(str(checkpoint), box_views / "box.bake", size=80)
    assert report.startswith(f"baked {len(baked)} splats") and (box_views / "box.bake").is_file()
    assert baked.baked_from == checkpoint.resolve() and baked.background == [0.0, 0.0, 0.0]
    splats = baked.splats
    n = len(baked)
    assert n > 100 and "sh" not in splats, n
    assert splats["positions"].shape == (n, 3) and splats["opacities"].shape == (n,)
    assert splats["colors"].min() >= 0 and splats["colors"].max() <= 1
    np.testing.assert_allclose(np.linalg.norm(splats["rotations"], axis=1), 1.0, atol=1e-3)
    # Its views are the field's, blurred at the box's edges by the splats' width (the command line's test:
    # 26.5 dB when written).
    untuned = np.mean([psnr(drawn(baked, i)[0], views["images"][i]) for i in range(4)])
    assert untuned > 24.0, untuned

    # Fine-tuned against the four views (with colors that change with the view), it takes its edges back.
    tuned, report = nerfjit.bake(str(checkpoint), box_views / "tuned.bake", size=80, tune=4)
    assert "tuning pass 1: 4 views" in report and tuned.splats["sh"].shape == (len(tuned), 3, 3)
    image, depth, opacity = drawn(tuned, 0)
    assert image.shape == (40, 40, 3) and depth.shape == (40, 40) and opacity.shape == (40, 40)
    assert image.dtype == np.float32 and 0.05 < opacity.mean() < 0.95
    scores = [psnr(drawn(tuned, i)[0], views["images"][i]) for i in range(4)]
    assert min(scores) > 35.0 and np.mean(scores) > untuned + 10, (untuned, scores)

    # Opened again from its file: the same splats, the same picture, bit for bit.
    again = nerfjit.Bake(box_views / "tuned.bake")
    for name, values in tuned.splats.items():
        np.testing.assert_array_equal(again.splats[name], values)
    np.testing.assert_array_equal(drawn(again, 2)[0], drawn(tuned, 2)[0])


def test_bad_bakes_say_what_is_wrong(box_views):
    script = trainer(box_views, steps=10)
    with pytest.raises(ValueError, match="sh_degree is 0 or 1"):
        nerfjit.bake(str(script), box_views / "x.bake", sh_degree=2)
    with pytest.raises(ValueError, match="tune"):
        nerfjit.bake(str(script), box_views / "x.bake", tune=-1)
    with pytest.raises(ValueError, match="min_weight"):
        nerfjit.bake(str(script), box_views / "x.bake", min_weight=float("nan"))
    with pytest.raises(nerfjit.NerfjitError, match=r"must end in \.bake"):
        nerfjit.bake(str(script), box_views / "x.ply")
    with pytest.raises(nerfjit.NerfjitError, match="nothing.bake"):
        nerfjit.Bake(box_views / "nothing.bake")
    (box_views / "broken.bake").write_bytes(b"not a safetensors file")
    with pytest.raises(nerfjit.NerfjitError, match="broken.bake"):
        nerfjit.Bake(box_views / "broken.bake")
