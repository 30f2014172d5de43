"""A few training steps on the tiny generated dataset: losses fall, runs checkpoint and resume."""

import json

import numpy as np
import torch

from cmr.data import find_sequences, list_frames, make_sample
from cmr.episodes import embed, gae, rollout
from cmr.train import Config, Run, main

SMALL = dict(num_points=4096, embed_points=4096, embed_batch=1, agent_envs=2, pool_size=2, pool_refresh=1,
             rollout_steps=3, minibatch=8, eval_frames=1, holdout_every=4, log_every=1, eval_every=0)


def small_run(tmp_path, data, **extra) -> Run:
    cfg = Config.from_overrides(Config(), [f"{k}={v}" for k, v in {**SMALL, **extra}.items()])
    cfg = Config(**{**cfg.__dict__, "data": str(data), "out": str(tmp_path)})
    return Run(cfg)


def test_embedding_loss_falls(tmp_path, tiny_dataset):
    torch.manual_seed(0)
    run = small_run(tmp_path, tiny_dataset)
    samples = [make_sample(run.train_frames[0], np.random.default_rng(0), train=True, num_points=4096)]
    for k in ("point_encoder", "image_encoder", "frustum_head"):
        run.models[k].train()
    losses = []
    for _ in range(12):
        loss, _ = run.embed_losses(samples)
        run.opt_embed.zero_grad()
        loss.backward()
        run.opt_embed.step()
        losses.append(loss.item())
    assert np.mean(losses[-3:]) < 0.85 * np.mean(losses[:3]), losses


def test_behaviour_cloning_loss_falls(tmp_path, tiny_dataset):
    torch.manual_seed(0)
    run = small_run(tmp_path, tiny_dataset)
    for m in run.models.values():
        m.eval()
    frames = run.train_frames[:2]
    eps = embed(run.models, [make_sample(f, np.random.default_rng(i), True, 4096) for i, f in enumerate(frames)], run.device)
    traj = rollout(run.models["agent"], eps, 4, "sample", 0.5, np.random.default_rng(0), torch.Generator().manual_seed(0))
    first = run.agent_update(eps, traj, ppo_weight=0.0)
    for _ in range(10):
        last = run.agent_update(eps, traj, ppo_weight=0.5)
    assert last["bc"] < 0.7 * first["bc"], (first, last)


def test_expert_rollout_converges(tiny_dataset):
    """The greedy expert (the BC teacher) reaches the truth on the protocol's samples."""
    frames = list_frames(find_sequences(tiny_dataset))
    from cmr import geometry as g
    from cmr.models import build_all
    eps = embed(build_all(), [make_sample(f, np.random.default_rng(i), False, 2048) for i, f in enumerate(frames)], "cpu")
    traj = rollout(None, eps, 10, "expert")
    for pose, truth in zip(traj.poses[-1], eps.truth):
        err = g.pose_error(pose, truth)
        assert err["rte_m"] < 0.3 and err["rre_geodesic_deg"] < 0.2
    assert (traj.rewards >= 0).mean() > 0.9  # expert steps rarely move away from the truth


def test_gae_matches_hand_computation():
    rewards = np.array([[0.5], [-0.5]], dtype=np.float32)
    values = np.array([[0.1], [0.2], [0.3]], dtype=np.float32)
    adv, ret = gae(rewards, values, gamma=0.9, lam=0.8)
    d1 = -0.5 + 0.9 * 0.3 - 0.2
    d0 = 0.5 + 0.9 * 0.2 - 0.1
    assert np.allclose(adv[:, 0], [d0 + 0.72 * d1, d1])
    assert np.allclose(ret, adv + values[:-1])


def test_cli_run_checkpoints_and_resumes(tmp_path, tiny_dataset):
    args = ["--data", str(tiny_dataset), "--out", str(tmp_path), "--set"] + [f"{k}={v}" for k, v in SMALL.items()]
    main(args + ["embed_steps=2", "agent_iters=1", "eval_every=1"])
    log = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert [r["stage"] for r in log].count("embed") == 2 and any(r["stage"] == "val" for r in log)
    assert (tmp_path / "last.pt").exists() and (tmp_path / "best.pt").exists()
    main(args + ["embed_steps=2", "agent_iters=2", "eval_every=0"])  # resumes: no embed steps redone
    log = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert [r["stage"] for r in log].count("embed") == 2
    assert [r["step"] for r in log if r["stage"] == "agent"] == [1, 2]


def test_copies_are_kept_aside_every_k_steps(tmp_path, tiny_dataset):
    args = ["--data", str(tiny_dataset), "--out", str(tmp_path), "--set"] + [f"{k}={v}" for k, v in SMALL.items()]
    main(args + ["embed_steps=3", "agent_iters=2", "keep_embed_every=2", "keep_agent_every=1"])
    assert sorted(p.name for p in (tmp_path / "snap").iterdir()) == ["agent_00001.pt", "agent_00002.pt", "embed_000002.pt"]
    kept = torch.load(tmp_path / "snap" / "agent_00001.pt", map_location="cpu", weights_only=False)
    assert (kept["embed_step"], kept["agent_iter"]) == (3, 1)
    assert not list((tmp_path / "snap").glob("*.tmp"))


def test_averaged_agent_lags_the_live_one_and_is_what_ships(tmp_path, tiny_dataset):
    from cmr.export import load_models
    args = ["--data", str(tiny_dataset), "--out", str(tmp_path), "--set"] + [f"{k}={v}" for k, v in SMALL.items()]
    main(args + ["embed_steps=1", "agent_iters=2", "agent_ema=0.5"])
    state = torch.load(tmp_path / "last.pt", map_location="cpu", weights_only=False)
    live, avg = state["models"]["agent"], state["agent_ema"]
    moved = [k for k in live if live[k].dtype.is_floating_point and not torch.equal(live[k], avg[k])]
    assert moved, "two updates at decay 0.5 must leave the average behind the live weights"
    shipped, _ = load_models(tmp_path / "last.pt")
    assert all(torch.equal(v, avg[k]) for k, v in shipped["agent"].state_dict().items())
    main(args + ["embed_steps=1", "agent_iters=3", "agent_ema=0.5"])  # resume keeps averaging, not restarting
    resumed = torch.load(tmp_path / "last.pt", map_location="cpu", weights_only=False)
    for k in moved:
        expected = avg[k].lerp(resumed["models"]["agent"][k], 0.5)
        assert torch.allclose(resumed["agent_ema"][k], expected), k


def test_degraded_image_features_stay_unit_and_keep_about_a_third_of_themselves():
    """`degrade_image_features` at the top noise keeps cells unit length and about 1 / sqrt(1 + 64
    sigma^2) of their original direction; share 0 leaves every row untouched; draws are seeded."""
    import numpy as np
    import torch

    from cmr.episodes import Episodes, degrade_image_features

    def episodes(seed):
        g = torch.Generator().manual_seed(seed)
        f = torch.randn(4, 64, 5, 7, generator=g)
        f = f / f.norm(dim=1, keepdim=True)
        return Episodes(points=torch.zeros(4, 8, 3), point_features=torch.zeros(4, 8, 64), image_features=f,
                        frustum_prob=torch.zeros(4, 8), intrinsics=torch.zeros(4, 4), truth=[None] * 4,
                        initial=[None] * 4, pivots=[None] * 4, reward_points=[None] * 4)

    clean = episodes(1)
    untouched = episodes(1)
    degrade_image_features(untouched, 0.0, 0.35, np.random.default_rng(0))
    assert torch.equal(untouched.image_features, clean.image_features)

    noisy = episodes(1)
    degrade_image_features(noisy, 1.0, 0.35, np.random.default_rng(0))
    assert torch.allclose(noisy.image_features.norm(dim=1), torch.ones(4, 5, 7), atol=1e-5)
    kept = (noisy.image_features * clean.image_features).sum(dim=1).mean(dim=(1, 2))
    assert (kept < 0.999).all() and (kept > 0.25).all(), kept  # sigma is drawn in [0, 0.35] per row
    again = episodes(1)
    degrade_image_features(again, 1.0, 0.35, np.random.default_rng(0))
    assert torch.equal(again.image_features, noisy.image_features)

    top = episodes(2)
    degrade_image_features(top, 1.0, 1e-9, np.random.default_rng(0))  # ~no noise: unchanged direction
    assert torch.allclose(top.image_features, episodes(2).image_features, atol=1e-6)
    # Each row keeps about 1 / sqrt(1 + 64 sigma^2) of itself for the sigma it drew (a third at
    # 0.35): the draws replayed in the function's order (share, sigma, noise per row).
    rng = np.random.default_rng(0)
    sigmas = []
    for _ in range(4):
        rng.random()
        sigmas.append(rng.uniform(0.0, 0.35))
        rng.standard_normal((64, 5, 7))
    expected = torch.tensor([1.0 / np.sqrt(1.0 + 64 * s ** 2) for s in sigmas], dtype=torch.float32)
    assert torch.allclose(kept, expected, atol=0.05), (kept, expected)
