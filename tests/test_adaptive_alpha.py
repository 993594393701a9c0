"""AdaptiveAlpha (paper eq. 12): formula, transform in a replay buffer, estimator modes."""

from __future__ import annotations

import re

import pytest
import torch
from tensordict import TensorDict
from test_value_expansion import actor_net, batch, critic_net, ensemble_loss, world_model
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torchrl_rave import AdaptiveAlpha, RAVEValueEstimator, ValueExpansionEstimator


class TestAdaptiveAlpha:
    def test_matches_hand_computed_error(self):
        wm = world_model(3)
        data = batch(B=10)
        obs, act, nxt = data["observation"], data["action"], data["next", "observation"]
        with torch.no_grad():
            mean, _ = wm.predict_transition(obs, act)  # [N, B, S], normalised deltas
            target = (nxt - obs - wm.delta_norm.mean) / wm.delta_norm.std
            err = ((mean.mean(0) - target) ** 2).sum(-1)
        expected = (1.5 * (1 - err / 2.0)).clamp_min(0)
        out = AdaptiveAlpha(wm, alpha=1.5, alpha_error_scale=2.0)(data)
        torch.testing.assert_close(out["rave_alpha"].squeeze(-1), expected)

    def test_perfect_model_gives_full_alpha_and_bad_model_zero(self):
        wm = world_model(2)
        data = batch(B=4)
        with torch.no_grad():
            pred = wm.step(data["observation"], data["action"], sample=False).mean(0)
        data["next", "observation"] = pred  # the model's own mean prediction: zero error
        torch.testing.assert_close(
            AdaptiveAlpha(wm, alpha=2.0)(data)["rave_alpha"],
            torch.full((4, 1), 2.0),
            rtol=1e-4,
            atol=1e-4,
        )
        data["next", "observation"] = pred + 100.0
        assert AdaptiveAlpha(wm, alpha=2.0)(data)["rave_alpha"].eq(0).all()

    def test_replay_buffer_transform_and_estimator_modes(self):
        wm = world_model(3)
        rb = TensorDictReplayBuffer(
            storage=LazyTensorStorage(100), transform=AdaptiveAlpha(wm, alpha=1.5), batch_size=16
        )
        rb.extend(batch(B=50))
        sample = rb.sample()
        assert sample["rave_alpha"].shape == (16, 1)
        loss = ensemble_loss()
        # "adaptive" computes the same alpha itself; "tensordict" reads the transform's
        torch.manual_seed(0)
        adaptive = RAVEValueEstimator.for_loss(loss, world_model=wm, gamma=0.9, alpha=1.5)
        from_td = RAVEValueEstimator.for_loss(
            loss, world_model=wm, gamma=0.9, alpha=1.5, alpha_mode="tensordict"
        )
        a_td, b_td = sample.clone(), sample.clone()
        del a_td["rave_alpha"]
        torch.manual_seed(1)
        a = adaptive.value_estimate(a_td)
        torch.manual_seed(1)
        b = from_td.value_estimate(b_td)
        torch.testing.assert_close(a_td["rave_alpha"], sample["rave_alpha"])
        torch.testing.assert_close(a, b)

    def test_tensordict_alpha_equals_constant(self):
        # K = 2 critics: with one critic V_0 = 0 and the mix ignores alpha (see the estimator docs)
        wm, actor, critics = world_model(2), actor_net(), [critic_net(), critic_net()]
        params = TensorDict.from_modules(*critics, as_module=True)
        kw = dict(
            world_model=wm,
            actor_network=actor,
            value_network=critics[0],
            value_params=params,
            gamma=0.9,
            rollout="mean",
        )
        data = batch(B=6)
        const = ValueExpansionEstimator(alpha=0.8, **kw).value_estimate(data.clone())
        data["value_expansion_alpha"] = torch.full((6, 1), 0.8)
        read = ValueExpansionEstimator(alpha_mode="tensordict", **kw).value_estimate(data)
        torch.testing.assert_close(read, const)
        # and a larger alpha gives a lower (more pessimistic) target
        data["value_expansion_alpha"] = torch.full((6, 1), 2.0)
        lower = ValueExpansionEstimator(alpha_mode="tensordict", **kw).value_estimate(data)
        assert (lower <= const + 1e-6).all() and (lower < const - 1e-6).any()

    @pytest.mark.parametrize(
        "kw,match", [({"alpha": -1.0}, "alpha"), ({"alpha_error_scale": 0.0}, "alpha_error_scale")]
    )
    def test_bad_arguments(self, kw, match):
        with pytest.raises(ValueError, match=match):
            AdaptiveAlpha(world_model(1), **kw)

    @pytest.mark.parametrize("key", ["action", ("next", "observation")])
    def test_a_missing_entry_is_named(self, key):
        # it failed with "unsupported operand type(s) for -: 'NoneType' and 'Tensor'"
        data = batch(B=4).exclude(key)
        with pytest.raises(ValueError, match=re.escape(f"no entry {key!r}")):
            AdaptiveAlpha(world_model(1))(data)

    def test_not_an_env_transform(self):
        with pytest.raises(RuntimeError, match="replay-buffer"):
            AdaptiveAlpha(world_model(1))._call(TensorDict())
