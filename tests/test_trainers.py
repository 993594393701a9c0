"""WorldModelTrainer: the schedule against a hand count, the step against a hand-written
one, checkpoints that continue the schedule, and the TorchRL Trainer hook."""

from __future__ import annotations

import copy

import pytest
import torch
from tensordict import TensorDict
from test_world_model import small_model, transitions
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torchrl_rave import WorldModelEnsembleLoss, WorldModelTrainer


def buffer(n=64):
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(n), batch_size=16)
    rb.extend(transitions(n))
    return rb


class TestWorldModelTrainer:
    @pytest.mark.parametrize("pretrain,every", [(0, 1), (3, 1), (2, 3)])
    def test_schedule(self, pretrain, every):
        trainer = WorldModelTrainer(small_model(), pretrain_updates=pretrain, train_every=every)
        rb = buffer()
        took = [trainer.step(rb) is not None for _ in range(7)]
        # the first call pretrains, then a step on calls 0, every, 2 every, ...
        assert trainer.updates == pretrain + len(range(0, 7, every))
        assert took == [pretrain > 0 or c % every == 0 for c in range(7)][:1] + [
            c % every == 0 for c in range(1, 7)
        ]
        assert trainer.calls == 7 and trainer.pretrained

    def test_update_equals_a_hand_written_step(self):
        batch = transitions(32)
        models = [small_model(), small_model()]
        models[1].load_state_dict(models[0].state_dict())
        trainer = WorldModelTrainer(models[0], lr=1e-3, pretrain_updates=0)
        opt = torch.optim.Adam(models[1].parameters(), lr=1e-3)
        loss = WorldModelEnsembleLoss(models[1])
        for _ in range(3):
            torch.manual_seed(4)  # the same bootstrap resample
            trainer.update(batch)
            torch.manual_seed(4)
            out = loss(batch)
            opt.zero_grad()
            (out["loss_transition"] + out["loss_reward"] + out["loss_termination"]).backward()
            opt.step()
        for a, b in zip(models[0].parameters(), models[1].parameters(), strict=True):
            torch.testing.assert_close(a, b)

    def test_what_it_samples_and_extends_goes_to_the_models_device(self, monkeypatch):
        """TorchRL's sota scripts keep the replay buffer on the CPU and the models on
        ``get_available_device()``: the batches must reach the model's device. A CPU-only
        machine stands in a second device with ``meta``, recording what each step and
        each normaliser update received instead of running it."""
        meta = torch.device("meta")
        trainer = WorldModelTrainer(small_model(), pretrain_updates=2)
        monkeypatch.setattr(WorldModelTrainer, "device", property(lambda self: meta))
        seen = []
        monkeypatch.setattr(trainer, "_update", lambda batch: seen.append(batch.device))
        monkeypatch.setattr(trainer.world_model, "update_normalizers_from",
                            lambda data: seen.append(data.device))  # fmt: skip
        rb = buffer()  # stored on the CPU
        trainer.extend(transitions(10))
        trainer.step(rb)  # two pretraining steps and one step
        trainer.update(transitions(8))
        assert seen == [meta] * 5

    def test_extend_updates_the_normalisers(self):
        wm = small_model()
        before = int(wm.obs_norm.count)
        WorldModelTrainer(wm).extend(transitions(10))
        assert int(wm.obs_norm.count) == before + 10

    def test_state_dict_continues_the_schedule(self):
        rb = buffer()
        a = WorldModelTrainer(small_model(), pretrain_updates=2, train_every=2)
        for _ in range(3):
            a.step(rb)
        b_model = small_model()
        b_model.load_state_dict(a.world_model.state_dict())
        b = WorldModelTrainer(b_model, pretrain_updates=2, train_every=2)
        b.load_state_dict(copy.deepcopy(a.state_dict()))  # as a checkpoint round trip
        assert (b.calls, b.updates, b.pretrained) == (3, 4, True)
        torch.manual_seed(0)
        a.step(rb)
        torch.manual_seed(0)
        b.step(rb)  # call 3: no step for either, and no second pretraining
        assert a.updates == b.updates == 4
        torch.manual_seed(1)
        a.step(rb)
        torch.manual_seed(1)
        b.step(rb)
        for p, q in zip(a.world_model.parameters(), b_model.parameters(), strict=True):
            torch.testing.assert_close(p, q)

    def test_a_stopped_pretraining_continues_where_it_stopped(self):
        """``pretrain(rb, stop)`` asks ``stop`` before each step: stopped after 2 of 5
        steps, its state says so, and a trainer loaded from it takes the other 3 and no
        more, ending with the weights of a pretraining never stopped."""
        rb = buffer()
        whole = WorldModelTrainer(small_model(), pretrain_updates=5)
        models = [small_model(), small_model()]
        for m in models:
            m.load_state_dict(whole.world_model.state_dict())
        torch.manual_seed(3)
        whole.pretrain(rb)
        asked = []
        first = WorldModelTrainer(models[0], pretrain_updates=5)
        torch.manual_seed(3)
        first.pretrain(rb, stop=lambda: asked.append(1) or len(asked) > 2)
        assert (first.pretrain_steps, first.updates, first.pretrained) == (2, 2, False)
        state = copy.deepcopy(first.state_dict())
        rng = torch.get_rng_state()
        assert state["pretrain_steps"] == 2 and not state["pretrained"]
        second = WorldModelTrainer(models[1], pretrain_updates=5)
        models[1].load_state_dict(models[0].state_dict())
        second.load_state_dict(state)
        torch.set_rng_state(rng)
        second.pretrain(rb)
        assert (second.pretrain_steps, second.updates, second.pretrained) == (5, 5, True)
        second.pretrain(rb)  # once only
        assert second.updates == 5
        for p, q in zip(whole.world_model.parameters(), models[1].parameters(), strict=True):
            assert torch.equal(p, q)
        # a checkpoint written before pretraining could stop holds only the flag
        old = {k: v for k, v in state.items() if k != "pretrain_steps"}
        for flag, steps in [(True, 5), (False, 0)]:
            trainer = WorldModelTrainer(small_model(), pretrain_updates=5)
            trainer.load_state_dict({**old, "pretrained": flag})
            assert trainer.pretrain_steps == steps

    def test_bad_settings(self):
        with pytest.raises(ValueError, match="train_every"):
            WorldModelTrainer(small_model(), train_every=0)
        with pytest.raises(ValueError, match="pretrain_updates"):
            WorldModelTrainer(small_model(), pretrain_updates=-1)
        for lr in (0.0, float("nan")):  # a NaN rate was taken, and made the model NaN
            with pytest.raises(ValueError, match="lr must be a finite number > 0"):
                WorldModelTrainer(small_model(), lr=lr)

    def test_torchrl_trainer_hook(self):
        """Registered on a TorchRL Trainer, collected batches reach the normalisers and
        every optimisation step trains the model on the replay buffer."""
        from torchrl.trainers import Trainer

        class OneBatchCollector:
            init_random_frames = 0

            def __iter__(self):
                yield transitions(20).unsqueeze(0)

            def set_seed(self, seed, static_seed=False):
                return seed

            def shutdown(self):
                pass

        class NoLoss(torch.nn.Module):
            def __init__(self):
                super().__init__()
                self.w = torch.nn.Parameter(torch.zeros(()))

            def forward(self, td):
                return TensorDict(loss_zero=(self.w * 0).sum())

        wm = small_model()
        rb = buffer()
        agent_loss = NoLoss()
        trainer = Trainer(
            collector=OneBatchCollector(),
            total_frames=20,
            frame_skip=1,
            optim_steps_per_batch=4,
            loss_module=agent_loss,
            optimizer=torch.optim.SGD(agent_loss.parameters(), lr=0.1),
            logger=None,
            progress_bar=False,
        )
        hook = WorldModelTrainer(wm, pretrain_updates=1)
        count = int(wm.obs_norm.count)
        hook.register(trainer, replay_buffer=rb)
        trainer.train()
        assert int(wm.obs_norm.count) == count + 20
        assert (hook.calls, hook.updates) == (4, 5)
