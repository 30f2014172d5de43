import pytest
import torch

from cmr.interpolate import interpolate


def checkpoint(agent_value: float, encoder_value: float = 1.0, ema: bool = True) -> dict:
    agent = {"fc.weight": torch.full((2, 3), agent_value), "fc.bias": torch.full((2,), agent_value), "steps": torch.tensor(7)}
    models = {name: {"w": torch.full((4,), encoder_value)} for name in ("point_encoder", "image_encoder", "frustum_head")}
    models["agent"] = {k: v + 100.0 if v.is_floating_point() else v for k, v in agent.items()}  # the raw agent, not shipped
    return {"models": models, "agent_ema": agent if ema else None, "opt_agent": {"state": {}}, "meta": {"training": {"run": "x"}}}


def test_the_ends_are_the_two_agents_and_the_middle_is_their_mean():
    start, tuned = checkpoint(0.0), checkpoint(2.0)
    assert torch.equal(interpolate(start, tuned, 0.0)["agent_ema"]["fc.weight"], start["agent_ema"]["fc.weight"])
    assert torch.equal(interpolate(start, tuned, 1.0)["agent_ema"]["fc.weight"], tuned["agent_ema"]["fc.weight"])
    mid = interpolate(start, tuned, 0.5)
    assert torch.allclose(mid["agent_ema"]["fc.bias"], torch.full((2,), 1.0))
    assert torch.equal(mid["models"]["agent"]["fc.weight"], mid["agent_ema"]["fc.weight"])  # export reads either
    assert mid["agent_ema"]["steps"].item() == 7 and mid["opt_agent"] is None
    assert tuned["agent_ema"]["fc.weight"][0, 0].item() == 2.0  # the inputs are left as they were


def test_the_raw_agent_mixes_when_a_run_kept_no_average():
    mid = interpolate(checkpoint(0.0, ema=False), checkpoint(2.0, ema=False), 0.25)
    assert torch.allclose(mid["models"]["agent"]["fc.weight"], torch.full((2, 3), 100.5))
    assert mid["agent_ema"] is None


def test_other_encoders_or_a_bad_alpha_are_refused():
    with pytest.raises(ValueError, match="image_encoder|point_encoder|frustum_head"):
        interpolate(checkpoint(0.0), checkpoint(2.0, encoder_value=3.0), 0.5)
    with pytest.raises(ValueError, match="alpha"):
        interpolate(checkpoint(0.0), checkpoint(2.0), 1.5)


def test_the_encoders_mix_under_the_agent_both_ship():
    start, tuned = checkpoint(1.0, encoder_value=0.0), checkpoint(1.0, encoder_value=4.0)
    for name in ("point_encoder", "image_encoder", "frustum_head"):
        start["models"][name]["batches"] = torch.tensor(3)  # an integer buffer: the tuned one's
        tuned["models"][name]["batches"] = torch.tensor(9)
    mid = interpolate(start, tuned, 0.75, part="encoders")
    for name in ("point_encoder", "image_encoder", "frustum_head"):
        assert torch.allclose(mid["models"][name]["w"], torch.full((4,), 3.0))
        assert mid["models"][name]["batches"].item() == 9
    assert torch.equal(mid["agent_ema"]["fc.weight"], tuned["agent_ema"]["fc.weight"])
    assert mid["meta"]["interpolated"]["part"] == "encoders"
    assert tuned["models"]["image_encoder"]["w"][0].item() == 4.0  # the inputs are left as they were


def test_encoders_under_different_agents_or_an_unknown_part_are_refused():
    with pytest.raises(ValueError, match="agents differ"):
        interpolate(checkpoint(0.0, encoder_value=0.0), checkpoint(2.0, encoder_value=4.0), 0.5, part="encoders")
    with pytest.raises(ValueError, match="part"):
        interpolate(checkpoint(0.0), checkpoint(2.0), 0.5, part="heads")
