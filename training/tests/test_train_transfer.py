"""The transfer recipe's training options: GroupNorm encoders export under the same contract, the
stage-1 schedule, loader workers draw the same batches, fine-tuning starts from a checkpoint."""

import json
import math

import numpy as np
import onnxruntime as ort
import pytest
import torch

from cmr import geometry as g
from cmr.export import CONTRACT_SHAPES, example_inputs, export_models, load_models
from cmr.models import build_all
from cmr.train import Config, Run, main
from test_train import SMALL, small_run


def test_group_norm_encoders_keep_the_onnx_contract(tmp_path):
    torch.manual_seed(0)
    models = build_all("group")
    assert any(isinstance(m, torch.nn.GroupNorm) for m in models["image_encoder"].modules())
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for k in ("image_encoder", "point_encoder")
                   for m in models[k].modules())
    for m in models.values():
        m.eval()
    doc = export_models({k: models[k] for k in ("point_encoder", "image_encoder")}, tmp_path, dict(data="test"))
    for name in ("point_encoder", "image_encoder"):
        sess = ort.InferenceSession(str(tmp_path / doc["graphs"][name]["file"]), providers=["CPUExecutionProvider"])
        inputs = example_inputs(name, num_points=3000)
        got = sess.run(None, {i.name: t.numpy() for i, t in zip(sess.get_inputs(), inputs)})[0]
        with torch.no_grad():
            want = models[name](*inputs).numpy()
        assert got.shape == want.shape
        assert np.abs(got - want).max() < 1e-4
        assert doc["graphs"][name]["inputs"] == CONTRACT_SHAPES[name][0]


def test_stage_one_schedule(tmp_path, tiny_dataset):
    run = small_run(tmp_path, tiny_dataset, embed_steps=100, embed_lr=2e-3, embed_lr_min=1e-5,
                    embed_schedule="cosine", embed_warmup=10)
    lrs = [run.embed_lr(s) for s in range(100)]
    assert lrs[0] == pytest.approx(2e-4) and lrs[9] == pytest.approx(2e-3)
    assert all(a >= b for a, b in zip(lrs[10:], lrs[11:])) and lrs[-1] < 1e-4
    assert run.embed_lr(50, progress=1.0) == pytest.approx(1e-5)
    const = small_run(tmp_path / "c", tiny_dataset)
    assert {const.embed_lr(s) for s in (0, 50, 99)} == {1e-3}


def test_loader_workers_draw_the_same_batches(tmp_path, tiny_dataset):
    extra = dict(photometric="heavy", scale_max=1.4, lidar_aug=True)
    inline = small_run(tmp_path / "a", tiny_dataset, **extra)
    pooled = small_run(tmp_path / "b", tiny_dataset, loader_workers=2, **extra)
    for step in (0, 1, 2):
        a, b = inline.samples(1, step, 2, 2048), pooled.samples(1, step, 2, 2048)
        for x, y in zip(a, b):
            assert np.array_equal(x.image, y.image) and np.array_equal(x.points, y.points)
    pooled._pool.shutdown(cancel_futures=True)


def test_group_norm_run_exports_and_fine_tunes(tmp_path, tiny_dataset):
    base = ["--data", str(tiny_dataset), "--set"] + [f"{k}={v}" for k, v in SMALL.items()]
    main(["--out", str(tmp_path / "src")] + base + ["embed_steps=2", "agent_iters=1", "norm=group",
                                                     "action_frame=map_z", "photometric=heavy", "lidar_aug=1"])
    models, meta = load_models(tmp_path / "src" / "last.pt")
    assert meta["config"]["norm"] == "group"
    assert any(isinstance(m, torch.nn.GroupNorm) for m in models["image_encoder"].modules())
    # Fine-tuning: a new run starts from the checkpoint's weights, with fresh counters.
    src = torch.load(tmp_path / "src" / "last.pt", map_location="cpu", weights_only=False)
    run = small_run(tmp_path / "ft", tiny_dataset, norm="group", init_from=str(tmp_path / "src" / "last.pt"))
    assert run.embed_step == 0 and run.agent_iter == 0
    for k, v in run.models["image_encoder"].state_dict().items():
        assert torch.equal(v, src["models"]["image_encoder"][k])
    with pytest.raises(SystemExit, match="norm=group"):
        small_run(tmp_path / "ft2", tiny_dataset, init_from=str(tmp_path / "src" / "last.pt"))
    # From the command line, `init_from` brings its architecture unless it is given (the shipped
    # model's fine-tune needs no `norm=` flag).
    main(["--out", str(tmp_path / "ft3")] + base + ["embed_steps=0", "agent_iters=1", f"init_from={tmp_path / 'src' / 'last.pt'}"])
    assert json.loads((tmp_path / "ft3" / "config.json").read_text())["norm"] == "group"
    # The agent alone from a checkpoint with other encoders (BatchNorm): encoders stay as given.
    main(["--out", str(tmp_path / "bn")] + base + ["embed_steps=1", "agent_iters=1", "agent_ema=0.9"])
    bn = torch.load(tmp_path / "bn" / "last.pt", map_location="cpu", weights_only=False)
    mixed = small_run(tmp_path / "mixed", tiny_dataset, norm="group", agent_ema=0.5,
                      init_from=str(tmp_path / "src" / "last.pt"), init_agent_from=str(tmp_path / "bn" / "last.pt"))
    for k, v in mixed.models["agent"].state_dict().items():
        assert torch.equal(v, bn["agent_ema"][k]) and torch.equal(mixed.agent_ema.state_dict()[k], v)
    assert any(not torch.equal(v, bn["models"]["agent"][k]) for k, v in bn["agent_ema"].items())
    for k, v in mixed.models["image_encoder"].state_dict().items():
        assert torch.equal(v, src["models"]["image_encoder"][k])


def test_stage_one_time_budget_ends_the_stage(tmp_path, tiny_dataset):
    main(["--data", str(tiny_dataset), "--out", str(tmp_path), "--set"] + [f"{k}={v}" for k, v in SMALL.items()]
         + ["embed_steps=1000", "embed_seconds=0.001", "agent_iters=1", "embed_schedule=cosine"])
    log = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert [r["stage"] for r in log].count("agent") == 1
    assert json.loads((tmp_path / "config.json").read_text())["embed_steps"] < 1000


def test_edge_channel_lives_inside_the_graph(tmp_path):
    torch.manual_seed(1)
    models = build_all("group", image_edges=True)
    enc = models["image_encoder"].eval()
    # A vertical step in the normalised image: gradient only along the step.
    img = torch.zeros(1, 3, 160, 512)
    img[..., 256:] = 1.0
    edges = enc.edge_map(img)[0, 0]
    assert edges[:, 250].max() < 0.01 and edges[:, 255:257].min() > 0.1
    doc = export_models({"image_encoder": enc}, tmp_path, dict(data="test"))
    assert doc["graphs"]["image_encoder"]["inputs"] == {"image": [1, 3, 160, 512]}
    sess = ort.InferenceSession(str(tmp_path / "image_encoder.onnx"), providers=["CPUExecutionProvider"])
    x = example_inputs("image_encoder", seed=3)[0]
    with torch.no_grad():
        want = enc(x).numpy()
    assert np.abs(sess.run(None, {"image": x.numpy()})[0] - want).max() < 1e-4
    # The edge input and GroupNorm stay well inside the 25 % FLOP budget of issue 13.
    base = export_models({"image_encoder": build_all()["image_encoder"].eval()}, tmp_path / "b", dict(data="test"))
    assert doc["graphs"]["image_encoder"]["flops"] < 1.25 * base["graphs"]["image_encoder"]["flops"]


def test_frozen_batch_norm_keeps_the_running_statistics(tmp_path, tiny_dataset):
    """`embed_frozen_bn`: stage 1 trains the weights but leaves every BatchNorm's running
    statistics (and so the function at step 0) as they were."""
    run = small_run(tmp_path, tiny_dataset, embed_steps=2, agent_iters=0, embed_frozen_bn=True)
    bns = [m for k in ("point_encoder", "image_encoder") for m in run.models[k].modules()
           if isinstance(m, torch.nn.BatchNorm2d)]
    assert bns
    before = [(m.running_mean.clone(), m.running_var.clone()) for m in bns]
    weights = run.models["image_encoder"].stem[0][0].weight.detach().clone()
    run.train_embed(deadline=float("inf"))
    assert all(torch.equal(m.running_mean, a) and torch.equal(m.running_var, b) for m, (a, b) in zip(bns, before))
    assert not torch.equal(run.models["image_encoder"].stem[0][0].weight, weights)
    thawed = small_run(tmp_path / "t", tiny_dataset, embed_steps=1, agent_iters=0)
    thawed.train_embed(deadline=float("inf"))
    assert not all(torch.equal(m.running_mean, torch.zeros_like(m.running_mean))
                   for k in ("image_encoder",) for m in thawed.models[k].modules() if isinstance(m, torch.nn.BatchNorm2d))


def test_rank_perturbations_near_and_wide(tmp_path, tiny_dataset):
    """Near perturbations turn 0-30 deg and move the camera 0.3-3 m; wide ones (`rank_far=1`)
    turn 30-180 deg about map z and move it at most `rank_far_shift_m` in the ground plane."""
    for far, turns, shifts in ((0.0, (0.0, 30.0), (0.3, 3.0)), (1.0, (30.0, 180.0), (0.0, 6.0))):
        run = small_run(tmp_path / str(far), tiny_dataset, rank_poses=64, rank_far=far)
        truth = run.samples(1, 0, 1, 2048)[0].truth
        centre = g.invert(truth)[:3, 3]
        for pose in run.rank_perturbations(truth, np.random.default_rng(0)):
            f0, f1 = g.ground_heading(truth)[1], g.ground_heading(pose)[1]
            turn = math.degrees(math.acos(np.clip(f0 @ f1, -1.0, 1.0)))
            moved = g.invert(pose)[:3, 3] - centre
            assert turns[0] - 1e-6 <= turn <= turns[1] + 1e-6
            assert shifts[0] - 1e-6 <= np.linalg.norm(moved) <= shifts[1] + 1e-6
            if far:
                assert abs(moved[2]) < 1e-9  # a ground shift: the camera keeps its height


@pytest.mark.parametrize("rank_far", [0.0, 1.0])
def test_rank_loss_prefers_the_truth_and_reaches_both_encoders(tmp_path, tiny_dataset, rank_far):
    """`rank_weight`: a ranking term on the alignment score; logged as `rank`, with gradients in
    the point and the image encoder; with near and with wide (`rank_far`) perturbations."""
    run = small_run(tmp_path, tiny_dataset, rank_weight=1.0, rank_poses=3, rank_far=rank_far)
    samples = run.samples(1, 0, 2, 2048)
    loss, stats = run.embed_losses(samples)
    assert "rank" in stats and stats["rank"] > 0
    loss.backward()
    for name in ("point_encoder", "image_encoder"):
        grads = [q.grad for q in run.models[name].parameters() if q.grad is not None]
        assert grads and any(g.abs().sum() > 0 for g in grads), name


def random_embeddings(sample):
    """`sample`'s points [N, 3] and intrinsics [4] as tensors, with seeded random unit point
    features [N, 64] and image features [64, 40, 128]."""
    torch.manual_seed(0)
    points = torch.as_tensor(sample.points[:, :3], dtype=torch.float32)
    pf = torch.nn.functional.normalize(torch.randn(len(points), 64), dim=1)
    imf = torch.nn.functional.normalize(torch.randn(64, 40, 128), dim=0)
    return points, torch.as_tensor(sample.intrinsics, dtype=torch.float32), pf, imf


def alignments(poses, points, k, pf, imf) -> list[float]:
    """`state.alignment` of each of `poses` (camera_from_map [4, 4]) with one sample's embeddings."""
    from cmr.state import alignment
    n = len(poses)
    return alignment(torch.as_tensor(np.stack(poses), dtype=torch.float32), points.expand(n, -1, -1),
                     k.expand(n, -1), pf.expand(n, -1, -1), imf.expand(n, -1, -1, -1)).tolist()


def best_scoring_negatives_train_both_encoders(run, sample, negatives, pool):
    """With random embeddings of `sample`, `negatives` (a `Run` method choosing hard negatives)
    returns the three best-scoring by `state.alignment` of the 12 poses `pool` draws with the same
    seed (the run's pool size is 12 and its count 3); and the ranking term with them has gradients
    in both encoders."""
    points, k, pf, imf = random_embeddings(sample)
    chosen = negatives(sample.truth, points, k, pf, imf, np.random.default_rng(2))
    drawn = pool(sample.truth, 12, np.random.default_rng(2))
    score = lambda poses: alignments(poses, points, k, pf, imf)  # noqa: E731
    assert np.allclose(score(chosen), sorted(score(drawn), reverse=True)[:3])
    loss, stats = run.embed_losses(run.samples(1, 0, 2, 2048))
    assert stats["rank"] > 0
    loss.backward()
    for name in ("point_encoder", "image_encoder"):
        assert any(q.grad is not None and q.grad.abs().sum() > 0 for q in run.models[name].parameters()), name


def test_hard_negatives_are_the_best_scoring_wrong_protocol_poses(tmp_path, tiny_dataset):
    """`rank_hard`: of `rank_hard_pool` protocol-like poses (none registered), the best-scoring by
    `state.alignment` join the ranking term's perturbed poses, which still trains both encoders."""
    run = small_run(tmp_path, tiny_dataset, rank_weight=1.0, rank_poses=2, rank_hard_pool=12, rank_hard=3)
    sample = run.samples(1, 0, 1, 2048)[0]
    pool = run.protocol_poses(sample.truth, 200, np.random.default_rng(1))
    assert len(pool) == 200 and not any(g.registered(p, sample.truth) for p in pool)
    centre = g.invert(sample.truth)[:3, 3]
    assert max(np.linalg.norm(g.invert(p)[:3, 3] - centre) for p in pool) <= 10.0 * math.sqrt(2) + 1e-6
    best_scoring_negatives_train_both_encoders(run, sample, run.hard_negatives, run.protocol_poses)


def test_near_negatives_are_the_best_scoring_poses_metres_off(tmp_path, tiny_dataset):
    """`rank_near_hard`: of `rank_near_pool` poses turned within 8 deg and shifted 1-5 m along the
    ground, the best-scoring join the ranking term with their own margin, which trains both
    encoders."""
    from cmr.train import NEAR_SHIFT_M, NEAR_TURN_DEG
    run = small_run(tmp_path, tiny_dataset, rank_weight=1.0, rank_poses=2, rank_near_pool=12, rank_near_hard=3)
    sample = run.samples(1, 0, 1, 2048)[0]
    centre = g.invert(sample.truth)[:3, 3]
    f0 = g.ground_heading(sample.truth)[1]
    for pose in run.near_poses(sample.truth, 200, np.random.default_rng(1)):
        moved = g.invert(pose)[:3, 3] - centre
        turn = math.degrees(math.acos(np.clip(f0 @ g.ground_heading(pose)[1], -1.0, 1.0)))
        assert 1.0 - 1e-6 <= np.linalg.norm(moved) <= NEAR_SHIFT_M + 1e-6 and abs(moved[2]) < 1e-9
        assert turn <= NEAR_TURN_DEG + 1e-6
    best_scoring_negatives_train_both_encoders(run, sample, run.near_negatives, run.near_poses)


# Each pool's settings (40 poses, the best 3, ranked on 300 points) and its `Run` methods: the
# chooser and the drawer it draws from.
SUBSET_POOLS = {
    "near": (dict(rank_near_pool=40, rank_near_hard=3, rank_near_points=300), "near_negatives", "near_poses"),
    "hard": (dict(rank_hard_pool=40, rank_hard=3, rank_hard_points=300), "hard_negatives", "protocol_poses"),
}


@pytest.mark.parametrize("kind", sorted(SUBSET_POOLS))
def test_negatives_scored_on_a_subset_of_points(tmp_path, tiny_dataset, kind):
    """`rank_near_points` / `rank_hard_points`: the pool is ranked on that many of the sample's
    points, a subset drawn after the pool from the same generator; the chosen poses are the best by
    the subset's score (and, with random embeddings, not all the best by the full score)."""
    settings, chooser, drawer = SUBSET_POOLS[kind]
    run = small_run(tmp_path, tiny_dataset, rank_weight=1.0, rank_poses=2, **settings)
    negatives, pool = getattr(run, chooser), getattr(run, drawer)
    sample = run.samples(1, 0, 1, 2048)[0]
    points, k, pf, imf = random_embeddings(sample)
    chosen = negatives(sample.truth, points, k, pf, imf, np.random.default_rng(5))
    rng = np.random.default_rng(5)
    drawn = pool(sample.truth, 40, rng)
    keep = np.sort(rng.choice(len(points), 300, replace=False))
    score = lambda poses, idx: alignments(poses, points[idx], k, pf[idx], imf)  # noqa: E731
    assert np.allclose(score(chosen, keep), sorted(score(drawn, keep), reverse=True)[:3])
    full_best = np.argsort(score(drawn, np.arange(len(points))))[::-1][:3]
    assert not all(any(np.array_equal(drawn[j], c) for c in chosen) for j in full_best)


def test_same_padding_is_tensorflows_and_keeps_shapes_static():
    from cmr.models import SamePad
    for k in (3, 5):
        x, w = torch.randn(1, 4, 40, 128), torch.randn(4, 1, k, k)
        before = (k - 2) // 2
        want = torch.nn.functional.conv2d(torch.nn.functional.pad(x, (before, k - 2 - before) * 2), w, stride=2, groups=4)
        got = torch.nn.functional.conv2d(SamePad(k, 2)(x), w, stride=2, groups=4)
        assert torch.equal(got, want)


def test_pretrained_backbone_loads_every_tensor_keeps_its_statistics_and_the_contract(tmp_path):
    from cmr.flops import count
    from cmr.models import LITE0_BLOCKS, LiteImageEncoder, lite_weights_path, load_pretrained
    import onnx
    enc = LiteImageEncoder(norm="group")
    want = torch.load(lite_weights_path(), map_location="cpu", weights_only=True)
    copied = load_pretrained(enc)
    # stem conv + BN (1 + 5), each block's convs (2 or 3) and BNs (5 each); block 0 has no expansion
    assert copied == 6 + sum((3 if e != 1 else 2) * 6 for e, *_ in LITE0_BLOCKS)
    assert torch.equal(enc.blocks[10].project[1].weight, want["_blocks.10._project_conv.weight"])
    mean = enc.stem[2].running_mean.clone()
    enc.train()
    assert all(not bn.training for bn in enc.blocks.modules() if isinstance(bn, torch.nn.BatchNorm2d))
    assert enc.smooth.training
    enc(torch.randn(2, 3, 160, 512)).sum().backward()
    assert torch.equal(enc.stem[2].running_mean, mean)
    enc.eval()
    doc = export_models({"image_encoder": enc}, tmp_path, dict(data="test"))
    graph = onnx.load(str(tmp_path / doc["graphs"]["image_encoder"]["file"]))
    flops, unresolved = count(graph, {})
    assert not unresolved and 0.8e9 < flops < 1.0e9
    sess = ort.InferenceSession(str(tmp_path / doc["graphs"]["image_encoder"]["file"]), providers=["CPUExecutionProvider"])
    image = example_inputs("image_encoder")[0]
    with torch.no_grad():
        assert np.abs(sess.run(None, {"image": image.numpy()})[0] - enc(image).numpy()).max() < 1e-4


def test_the_deep_encoder_starts_as_the_shallow_one_and_exports(tmp_path):
    from cmr.flops import count
    from cmr.models import LITE0_BLOCKS, LITE0_BLOCKS_S32, LiteImageEncoder, lite_weights_path, load_pretrained
    import onnx
    torch.manual_seed(0)
    shallow = LiteImageEncoder(norm="group")
    for p in shallow.parameters():  # not the lateral layers' default init: any weights
        p.data.normal_(0, 0.05)
    deep = LiteImageEncoder(norm="group", deep=True)
    pretrained = load_pretrained(deep)
    assert pretrained == 6 + sum((3 if e != 1 else 2) * 6 for e, *_ in LITE0_BLOCKS + LITE0_BLOCKS_S32)
    assert deep.load_shallow(shallow.state_dict()) == len(shallow.state_dict())
    want = torch.load(lite_weights_path(), map_location="cpu", weights_only=True)
    assert torch.equal(deep.blocks[15].project[1].weight, want["_blocks.15._project_conv.weight"])
    assert torch.equal(deep.blocks[10].project[1].weight, shallow.blocks[10].project[1].weight)
    image = torch.randn(1, 3, 160, 512)
    with torch.no_grad():
        # equal up to rounding: a convolution over more channels (zeros) may block its sums differently
        torch.testing.assert_close(deep.eval()(image), shallow.eval()(image), rtol=0, atol=1e-6)
    # the zero weights are trainable: one step moves them, and the output with them
    deep.train()
    (deep(image) * torch.randn(1, 64, 40, 128)).sum().backward()
    assert deep.lateral16[0].weight.grad[:, 112:].abs().sum() > 0
    with pytest.raises(ValueError, match="shape"):
        LiteImageEncoder(norm="batch", deep=True).load_shallow({"lateral16.0.weight": torch.zeros(64, 100, 1, 1)})
    deep.eval()
    doc = export_models({"image_encoder": deep}, tmp_path, dict(data="test"))
    graph = onnx.load(str(tmp_path / doc["graphs"]["image_encoder"]["file"]))
    flops, unresolved = count(graph, {})
    assert not unresolved and 1.0e9 < flops < 1.4e9, flops
    sess = ort.InferenceSession(str(tmp_path / doc["graphs"]["image_encoder"]["file"]), providers=["CPUExecutionProvider"])
    with torch.no_grad():
        assert np.abs(sess.run(None, {"image": image.numpy()})[0] - deep(image).numpy()).max() < 1e-4


def test_the_fine_point_encoder_starts_as_the_coarse_one_and_exports(tmp_path):
    from cmr.models import FINE_WIDTH, PointEncoder
    torch.manual_seed(0)
    coarse = PointEncoder(norm="group")
    for p in coarse.parameters():  # any weights, not the default init
        p.data.normal_(0, 0.1)
    fine = PointEncoder(norm="group", fine=True)
    assert fine.load_coarse(coarse.state_dict()) == len(coarse.state_dict())
    points = torch.randn(1, 3000, 3) * torch.tensor([20.0, 20.0, 2.0])
    with torch.no_grad():
        torch.testing.assert_close(fine.eval()(points), coarse.eval()(points), rtol=0, atol=1e-6)
    # the zero weights are trainable, and the fine branch learns through them
    fine.train()
    (fine(points) * torch.randn(1, 3000, 64)).sum().backward()
    assert fine.head[0][0].weight.grad[:, -FINE_WIDTH:].abs().sum() > 0
    with pytest.raises(ValueError, match="shape"):
        PointEncoder(norm="group", fine=True).load_coarse({"head.0.0.weight": torch.zeros(64, 10)})
    with pytest.raises(ValueError, match="not in this encoder"):
        PointEncoder(norm="group", fine=True).load_coarse({"blocks.0.weight": torch.zeros(1)})
    # a trained fine branch changes the answer, and the exported graph computes it for any N
    with torch.no_grad():
        fine.head[0][0].weight[:, -FINE_WIDTH:].normal_(0, 0.1)
    fine.eval()
    doc = export_models({"point_encoder": fine}, tmp_path, dict(data="test"))
    sess = ort.InferenceSession(str(tmp_path / doc["graphs"]["point_encoder"]["file"]), providers=["CPUExecutionProvider"])
    for n in (500, 4096):
        pts = torch.randn(1, n, 3) * torch.tensor([25.0, 25.0, 2.0])
        with torch.no_grad():
            want = fine(pts)
        assert not torch.allclose(want, coarse.eval()(pts), atol=1e-3)
        assert np.abs(sess.run(None, {"points": pts.numpy()})[0] - want.numpy()).max() < 1e-4


def test_a_run_swaps_a_lite0_backbone_for_lite1_keeping_the_rest_of_the_model(tmp_path, tiny_dataset):
    from cmr.models import LITE1_BLOCKS, lite_weights_path
    lite0 = small_run(tmp_path / "lite0", tiny_dataset, norm="group", image_backbone="efficientnet_lite0")
    for p in lite0.models["image_encoder"].parameters():  # a trained decoder: any weights
        p.data.normal_(0, 0.05)
    lite0.save("last.pt")
    lite1 = small_run(tmp_path / "lite1", tiny_dataset, norm="group", image_backbone="efficientnet_lite1",
                      init_from=str(lite0.dir / "last.pt"))
    enc = lite1.models["image_encoder"]
    assert len(enc.blocks) == len(LITE1_BLOCKS) == 15 and enc.variant == "efficientnet_lite1"
    want = torch.load(lite_weights_path("efficientnet_lite1"), map_location="cpu", weights_only=True)
    assert torch.equal(enc.blocks[14].project[1].weight, want["_blocks.14._project_conv.weight"])
    old = lite0.models["image_encoder"].state_dict()
    for k, v in enc.state_dict().items():
        if not k.startswith(("stem.", "blocks.")):
            assert torch.equal(v, old[k]), k
    for k in ("point_encoder", "frustum_head", "agent"):
        for name, v in lite1.models[k].state_dict().items():
            assert torch.equal(v, lite0.models[k].state_dict()[name]), (k, name)
    image = torch.randn(1, 3, 160, 512)
    with torch.no_grad():
        assert enc.eval()(image).shape == (1, 64, 40, 128)


def test_a_run_grows_a_fine_point_grid_from_a_coarse_checkpoint(tmp_path, tiny_dataset):
    coarse = small_run(tmp_path / "coarse", tiny_dataset, norm="group")
    coarse.save("last.pt")
    grown = small_run(tmp_path / "fine", tiny_dataset, norm="group", point_encoder="pillars_fine",
                      init_from=str(coarse.dir / "last.pt"))
    points = torch.randn(1, 2000, 3) * torch.tensor([20.0, 20.0, 2.0])
    a, b = coarse.models["point_encoder"].eval(), grown.models["point_encoder"].eval()
    with torch.no_grad():
        torch.testing.assert_close(a(points), b(points), rtol=0, atol=1e-6)
    assert grown.models["point_encoder"].fine is not None


def test_a_pretrained_backbone_run_trains_its_backbone_slower_and_resumes(tmp_path, tiny_dataset):
    from cmr.models import load_pretrained
    run = small_run(tmp_path, tiny_dataset, norm="group", image_backbone="efficientnet_lite0", backbone_lr_scale=0.1)
    fresh = build_all("group", image_backbone="efficientnet_lite0")["image_encoder"]
    load_pretrained(fresh)
    for k, v in fresh.state_dict().items():
        if k.startswith(("stem", "blocks")):
            assert torch.equal(v, run.models["image_encoder"].state_dict()[k])
    groups = run.opt_embed.param_groups
    assert [g_["lr_scale"] for g_ in groups] == [1.0, 0.1]
    assert len(groups[1]["params"]) == len(run.models["image_encoder"].backbone_parameters())
    base = ["--data", str(tiny_dataset), "--out", str(tmp_path / "cli"), "--set"] + [f"{k}={v}" for k, v in SMALL.items()]
    base += ["norm=group", "image_backbone=efficientnet_lite0", "embed_lr=1e-3"]
    main(base + ["embed_steps=1", "agent_iters=0"])
    state = torch.load(tmp_path / "cli" / "last.pt", map_location="cpu", weights_only=False)
    assert [g_["lr"] for g_ in state["opt_embed"]["param_groups"]] == pytest.approx([1e-3, 1e-4])
    models, meta = load_models(tmp_path / "cli" / "last.pt")
    assert meta["config"]["image_backbone"] == "efficientnet_lite0"
    assert type(models["image_encoder"]).__name__ == "LiteImageEncoder"
    main(base + ["embed_steps=2", "agent_iters=0"])  # resumes with the backbone's own group
    log = [json.loads(line) for line in (tmp_path / "cli" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log if r["stage"] == "embed"] == [1, 2]


def test_distillation_pulls_towards_a_frozen_teacher_and_trains_the_student_alone(tmp_path, tiny_dataset):
    """`distill_weight`: the teacher is `distill_from`'s encoders, frozen; the term (logged as
    `distill`) is 0 for a student equal to the teacher, grows as the student moves away, and its
    gradient reaches the student's encoders and never the teacher's."""
    main(["--out", str(tmp_path / "t"), "--data", str(tiny_dataset), "--set"]
         + [f"{k}={v}" for k, v in SMALL.items()] + ["embed_steps=0", "agent_iters=0"])
    teacher = str(tmp_path / "t" / "last.pt")
    run = small_run(tmp_path / "s", tiny_dataset, init_from=teacher, distill_weight=1.0, distill_from=teacher)
    for m in run.models.values():
        m.eval()  # the teacher's mode: equal weights give equal embeddings
    samples = run.samples(1, 0, 2, 2048)
    points = torch.as_tensor(np.stack([s.points for s in samples]))
    images = torch.as_tensor(np.stack([s.image for s in samples]))
    pf, imf = run.models["point_encoder"](points), run.models["image_encoder"](images)
    assert run.distill_loss(points, images, pf, imf).item() == pytest.approx(0.0, abs=1e-5)
    with torch.no_grad():
        for q in run.models["point_encoder"].parameters():
            q.add_(0.5 * torch.randn_like(q))
    pf = run.models["point_encoder"](points)
    moved = run.distill_loss(points, images, pf, imf)
    assert moved.item() > 0.01
    loss, stats = run.embed_losses(samples)
    assert stats["distill"] > 0.01
    loss.backward()
    for name in ("point_encoder", "image_encoder"):
        assert any(q.grad is not None and q.grad.abs().sum() > 0 for q in run.models[name].parameters()), name
        assert all(q.grad is None and not q.requires_grad for q in run.teacher[name].parameters()), name
    with pytest.raises(SystemExit, match="architecture"):
        small_run(tmp_path / "x", tiny_dataset, norm="group", distill_weight=1.0, distill_from=teacher)


def test_the_intensity_point_encoder_starts_as_the_plain_one_and_exports(tmp_path):
    from cmr.models import PointEncoder
    torch.manual_seed(0)
    plain = PointEncoder(norm="group")
    for p in plain.parameters():
        p.data.normal_(0, 0.1)
    lit = PointEncoder(norm="group", intensity=True)
    assert lit.in_channels == 4 and plain.in_channels == 3
    assert lit.load_coarse(plain.state_dict()) == len(plain.state_dict())
    points = torch.randn(1, 3000, 3) * torch.tensor([20.0, 20.0, 2.0])
    ranked = torch.cat([points, torch.rand(1, 3000, 1)], -1)
    with torch.no_grad():
        torch.testing.assert_close(lit.eval()(ranked), plain.eval()(points), rtol=0, atol=1e-6)
    lit.train()
    (lit(ranked) * torch.randn(1, 3000, 64)).sum().backward()
    assert lit.local[0][0].weight.grad[:, -1].abs().sum() > 0  # the intensity column learns
    with torch.no_grad():
        lit.local[0][0].weight[:, -1].normal_(0, 0.5)
    lit.eval()
    doc = export_models({"point_encoder": lit}, tmp_path, dict(data="test"))
    assert doc["graphs"]["point_encoder"]["inputs"] == {"points": [1, "N", 4]}
    assert doc["points"]["channels"] == ["x", "y", "z", "intensity_rank"]
    sess = ort.InferenceSession(str(tmp_path / doc["graphs"]["point_encoder"]["file"]), providers=["CPUExecutionProvider"])
    for n in (500, 4096):
        pts = torch.cat([torch.randn(1, n, 3) * torch.tensor([25.0, 25.0, 2.0]), torch.rand(1, n, 1)], -1)
        with torch.no_grad():
            want = lit(pts)
            flat = lit(torch.cat([pts[..., :3], torch.full((1, n, 1), 0.5)], -1))
        assert not torch.allclose(want, flat, atol=1e-3)  # the intensity changes the features
        assert np.abs(sess.run(None, {"points": pts.numpy()})[0] - want.numpy()).max() < 1e-4
    plain_doc = export_models({"point_encoder": plain.eval()}, tmp_path / "plain", dict(data="test"))
    assert plain_doc["graphs"]["point_encoder"]["inputs"] == {"points": [1, "N", 3]} and "channels" not in plain_doc["points"]


def test_a_run_grows_an_intensity_input_from_a_plain_checkpoint_and_trains_it(tmp_path, tiny_dataset):
    plain = small_run(tmp_path / "plain", tiny_dataset, norm="group")
    plain.save("last.pt")
    grown = small_run(tmp_path / "lit", tiny_dataset, norm="group", point_encoder="pillars_intensity",
                      init_from=str(plain.dir / "last.pt"), intensity_drop_p=0.5)
    enc = grown.models["point_encoder"]
    assert enc.intensity and grown.augment.intensity_drop_p == 0.5
    points = torch.randn(1, 2000, 3) * torch.tensor([20.0, 20.0, 2.0])
    with torch.no_grad():
        torch.testing.assert_close(plain.models["point_encoder"].eval()(points),
                                   enc.eval()(torch.cat([points, torch.rand(1, 2000, 1)], -1)), rtol=0, atol=1e-6)
    # stage 1 reads the samples' intensity ranks, and its loss reaches the new column
    from cmr.data import make_sample
    samples = [make_sample(f, np.random.default_rng(i), train=True, num_points=2048) for i, f in enumerate(grown.train_frames[:2])]
    enc.train()
    loss, _ = grown.embed_losses(samples)
    loss.backward()
    assert enc.local[0][0].weight.grad[:, -1].abs().sum() > 0
