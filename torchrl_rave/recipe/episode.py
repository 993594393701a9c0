"""The training episode in progress as a checkpoint component, so that a resumed run
continues the very episode it was in (every ``collector.backend``).

Two things carry an episode from one batch to the next: the env (its simulator, wrappers
and random generators, rebuilt by :class:`~torchrl_rave.envs.EpisodeReplay`) and
TorchRL's collector, which keeps the step it will act on next (the observation, the step
count, the episode's return so far). :class:`EpisodeCheckpoint` saves both, and restores
both into a new collector. A worker of a ``process`` or ``ray`` collector holds its own
env, collector step and random state (which draws its exploration noise);
:class:`EpisodeWorkerCollector` hands the three to the learner's process and takes them
back. Resumed this way, a run gives the numbers of the run that was never stopped.
"""

from __future__ import annotations

import sys
import warnings

import torch
from tensordict import TensorDict
from torchrl.checkpoint import GlobalRNGState
from torchrl.collectors import Collector, MultiSyncCollector

from torchrl_rave.envs.episode_replay import EpisodeReplay, EpisodeReplayError

__all__ = [
    "EpisodeCheckpoint",
    "EpisodeNotRestored",
    "EpisodeWorkerCollector",
    "continue_episode",
    "episode_recorder",
    "episode_state",
    "resume_collecting",
]


class EpisodeNotRestored(UserWarning):
    """A resumed run could not continue the episode its checkpoint was taken in, and
    continues from a new episode instead."""


def episode_recorder(env) -> EpisodeReplay | None:
    """The :class:`~torchrl_rave.envs.EpisodeReplay` of a TorchRL env built by
    :func:`~torchrl_rave.recipe.make_env` with ``record_episode=True``, or ``None``."""
    base = getattr(env, "base_env", env)
    gym_env = getattr(base, "_env", None)
    return gym_env if isinstance(gym_env, EpisodeReplay) else None


def _carrier(collector) -> TensorDict | None:
    # TorchRL's Collector keeps the next step to act on here; it has no public accessor
    if not isinstance(collector, Collector):
        return None
    return getattr(collector, "_carrier", None)


def _has_workers(collector) -> bool:
    """Whether ``collector`` collects in worker processes (``MultiSyncCollector``) or Ray
    actors (``RayCollector``), whose inner collectors answer ``map_fn``."""
    if isinstance(collector, MultiSyncCollector):
        return True
    ray = sys.modules.get("torchrl.collectors.distributed.ray")  # loaded if one exists
    return ray is not None and isinstance(collector, ray.RayCollector)


def _traj_pool(collector):
    """The pool that numbers ``collector``'s trajectories (a worker collector's is shared
    by its workers), or ``None`` where it numbers none."""
    if isinstance(collector, Collector) and not getattr(collector, "track_traj_ids", False):
        return None
    return getattr(collector, "_traj_pool", None)


class EpisodeCheckpoint:
    """The episode in progress of a run's training env and its collector, as a
    checkpoint component (``state_dict``/``load_state_dict``, plain data and tensors).

    ``attach`` names the env and collector whose episode ``state_dict`` saves;
    ``attach(None, None)`` says that the run starts new episodes next (a curriculum's new
    stage, in new envs), which a resumed run then does too.
    ``load_state_dict`` keeps a saved episode until :meth:`restore` rebuilds it in
    a new collector: the direct collector's, or each worker's of a ``MultiSyncCollector``
    or ``RayCollector`` of :class:`EpisodeWorkerCollector` workers. An episode that
    cannot be saved (an env without an ``EpisodeReplay``, workers that act with older
    weights than the learner's) is saved as ``{"kept": False}``, with why.
    """

    def __init__(self) -> None:
        self.env = None
        self.collector = None
        self.saved: dict | None = None
        #: whether the workers of a ``process`` or ``ray`` collector act with weights
        #: older than the learner's (set by the training loop: copies, Ray's or a GPU
        #: learner's, not pushed since the last update); their episode is then not kept,
        #: as a resumed run pushes the current weights
        self.workers_behind = False

    def attach(self, env, collector) -> None:
        self.env, self.collector = env, collector

    def state_dict(self) -> dict:
        if self.env is None and self.collector is None:  # detached: new episodes next
            return {"kept": False, "new_episode": True}
        if _has_workers(self.collector):
            state = self._workers_state()
        else:
            state = episode_state(self.env, self.collector)
        pool = _traj_pool(self.collector)
        if state["kept"]:
            state["traj_id"] = None if pool is None else pool.state_dict()["traj_id"]
        return state

    def _workers_state(self) -> dict:
        if self.workers_behind:
            return {"kept": False, "why": "the workers acted with older weights than the "
                    "learner's (collector.weight_sync_every > 1)"}  # fmt: skip
        try:
            states = self.collector.map_fn("episode_state")
        except Exception as err:  # noqa: BLE001 (the checkpoint is written all the same)
            return {"kept": False, "why": f"the workers gave no episode ({type(err).__name__}: "
                    f"{err})"}  # fmt: skip
        for i, state in enumerate(states):
            if not state["kept"]:
                return {"kept": False, "why": f"worker {i}: {state['why']}"}
        return {"kept": True, "workers": states}

    def load_state_dict(self, state: dict) -> None:
        self.saved = state

    def restore(self, env, collector) -> str | None:
        """Rebuilds the saved episode in ``env`` and hands ``collector`` its next step (a
        ``process`` or ``ray`` collector: each worker its own); returns ``None`` when it
        did, or why it could not (then ``env`` and ``collector`` must be reset: the
        caller does). Uses the saved episode once."""
        saved, self.saved = self.saved, None
        if saved is None:
            return "its checkpoint holds no episode (written before episodes were kept)"
        if not saved.get("kept"):
            return f"its checkpoint holds no episode: {saved.get('why', 'not kept')}"
        if _has_workers(collector):
            why = _continue_workers(saved.get("workers"), collector)
        elif saved.get("workers") is not None:
            why = "its checkpoint holds the episodes of worker processes"
        else:
            why = continue_episode(saved, env, collector)
        pool = _traj_pool(collector)
        if why is None and pool is not None and isinstance(saved.get("traj_id"), torch.Tensor):
            # the next trajectory's id, as the collector that was stopped would give it
            pool.load_state_dict({"traj_id": saved["traj_id"]})
        return why


def _continue_workers(workers, collector) -> str | None:
    """Each worker's saved episode (:meth:`EpisodeWorkerCollector.episode_state`) back in
    that worker of ``collector``; ``None``, or why not."""
    if not isinstance(workers, list) or len(workers) != collector.num_workers:
        count = len(workers) if isinstance(workers, list) else "no"
        return (f"its checkpoint holds {count} workers' episodes, the collector has "
                f"{collector.num_workers} workers")  # fmt: skip
    try:
        answers = collector.map_fn("continue_episode", [(w,) for w in workers])
    except Exception as err:  # noqa: BLE001 (the run starts new episodes instead)
        return f"the workers took no episode back ({type(err).__name__}: {err})"
    for i, why in enumerate(answers):
        if why is not None:
            return f"worker {i}: {why}"
    return None


def episode_state(env, collector) -> dict:
    """The episode in progress of ``env``, stepped by the in-process ``collector``, as
    plain data and tensors: ``{"kept": True, ...}`` with the episode's record and the
    collector's next step, or ``{"kept": False, "why": ...}``."""
    recorder = episode_recorder(env)
    carrier = _carrier(collector)
    if recorder is None or carrier is None:
        return {"kept": False, "why": "the collector's envs live in other processes"}
    episode = recorder.episode_state()
    if episode is None:
        return {"kept": False, "why": f"the episode was not recorded ({recorder.why_not})"}
    keys = sorted(carrier.keys(include_nested=True, leaves_only=True), key=str)
    return {
        "kept": True,
        "reset": episode["reset"],
        "actions": torch.from_numpy(episode["actions"]),
        "dtype": episode["dtype"],
        "carrier_keys": [list(k) if isinstance(k, tuple) else [k] for k in keys],
        "carrier_values": [carrier.get(k).detach().cpu().clone() for k in keys],
    }


def continue_episode(saved: dict, env, collector) -> str | None:
    """Rebuilds the episode of ``saved`` (from :func:`episode_state`) in ``env`` and sets
    ``collector``'s next step to the saved one; returns ``None`` when it did, or why it
    could not."""
    recorder, carrier = episode_recorder(env), _carrier(collector)
    if recorder is None or carrier is None:
        return "this env or collector cannot take an episode back"
    try:
        options = saved["reset"]["options"]
        keys = [tuple(k) if len(k) > 1 else k[0] for k in saved["carrier_keys"]]
        target = dict(zip(keys, saved["carrier_values"], strict=True))
        state = {"reset": saved["reset"], "actions": saved["actions"].numpy(),
                 "dtype": saved["dtype"]}  # fmt: skip
    except (AttributeError, KeyError, TypeError, ValueError) as err:
        return f"its episode record is unusable ({type(err).__name__}: {err})"
    if options is not None:
        # the recipe resets without options; a run directory's values are not handed
        # to the env, which may open them as files (recipe.trust)
        return "its episode began with reset options, which the recipe never passes"
    if not all(isinstance(v, torch.Tensor) for v in target.values()):
        return "its episode record is unusable (a collector entry is not a tensor)"
    # a new collector's step holds what a reset gives; the saved one also what the
    # policy wrote into it at the last step (overwritten at the next, but kept as is)
    now = carrier.keys(include_nested=True, leaves_only=True)
    missing = set(now) - set(keys)
    if missing:
        return f"the checkpoint's collector step lacks {sorted(map(str, missing))}"
    for key in now:
        value, current = target[key], carrier.get(key)
        if (value.shape, value.dtype) != (current.shape, current.dtype):
            return f"the checkpoint's collector step holds another {key!r}"
    try:
        obs = recorder.replay(state)
    except EpisodeReplayError as err:
        return str(err)
    observation = target.get("observation")
    if observation is not None:
        replayed = torch.as_tensor(obs).to(observation.dtype).reshape(observation.shape)
        if not torch.equal(replayed, observation):
            return "the replayed episode does not end at the checkpoint's observation"
    for key, value in target.items():
        current = carrier.get(key, None)
        device = current.device if current is not None else carrier.device or "cpu"
        carrier.set(key, value.to(device))
    return None


class EpisodeWorkerCollector(Collector):
    """TorchRL's ``Collector`` as the worker of a ``MultiSyncCollector`` or a
    ``RayCollector`` (``collector_class=``) whose episode a checkpoint can keep: its env
    must be built with ``record_episode=True``. The learner's process calls the two
    methods below in every worker through the collector's ``map_fn``, between batches,
    while the workers wait.

    Besides the episode and the collector's next step, a worker keeps the state of its
    process's torch generator, from which its policy draws the exploration noise (and
    the random actions of the first frames).
    """

    def episode_state(self) -> dict:
        """:func:`episode_state` of this worker, with its torch random state (``rng``)."""
        state = episode_state(self.env, self)
        if state["kept"]:
            state["rng"] = torch.get_rng_state()
        return state

    def continue_episode(self, saved: dict) -> str | None:
        """:func:`continue_episode` in this worker, then its torch random state set back
        to the saved one; returns why not, or ``None``."""
        rng = saved.get("rng") if isinstance(saved, dict) else None
        if not isinstance(rng, torch.Tensor) or rng.dtype != torch.uint8 or rng.dim() != 1:
            return "its episode record holds no usable random state of the worker"
        why = continue_episode(saved, self.env, self)
        if why is None:
            torch.set_rng_state(rng)
        return why


def resume_collecting(
    episode: EpisodeCheckpoint, env, collector, seed: int, rng_state: dict
) -> bool:
    """What a resumed run does with its first collector: continues the episode of the
    checkpoint just loaded into ``episode`` (each worker's, for a collector of workers);
    where it cannot (:class:`EpisodeNotRestored` says why), or where the run was about to
    start new episodes anyway, reseeds ``env`` (and the workers) with ``seed`` and starts
    a new episode. Then sets the random state back to ``rng_state``, the checkpoint's,
    whatever building the collector drew. Returns whether the episode was continued."""
    continued = _restore_or_restart(episode, env, collector, seed)
    GlobalRNGState().load_state_dict(rng_state)
    return continued


def _restore_or_restart(episode: EpisodeCheckpoint, env, collector, seed: int) -> bool:
    planned = bool(episode.saved and episode.saved.get("new_episode"))
    why = None if planned else episode.restore(env, collector)
    if why is None and not planned:
        return True
    episode.saved = None
    if not planned:
        warnings.warn(
            f"the resumed run starts a new episode: the episode its checkpoint was taken "
            f"in could not be continued ({why})",
            EpisodeNotRestored,
            stacklevel=3,
        )
    env.set_seed(seed)
    if _has_workers(collector):  # reseeds and resets each worker's env and stream
        collector.set_seed(seed)
    else:
        collector.reset()
    return False
