"""Collectors for the learner: in-process, worker processes or Ray actors, with weight pushes."""

from __future__ import annotations

import contextlib
import functools
import logging
import signal
import threading
from collections.abc import Callable, Iterator

import torch
from omegaconf import DictConfig
from tensordict import TensorDict, TensorDictBase
from torchrl.collectors import Collector, MultiSyncCollector

from torchrl_rave.recipe.agent import make_actor, make_env
from torchrl_rave.recipe.config import ALGORITHMS, check_ray_fits
from torchrl_rave.recipe.episode import EpisodeWorkerCollector
from torchrl_rave.recipe.trust import reach_ray_address


def make_collector(cfg: DictConfig, env, policy, device, frames_done: int = 0):
    """A collector for the frames still to go (``frames_done`` > 0 when resuming): the
    batches of ``collector.frames_per_batch`` frames an uninterrupted run collects from
    frame 0, the last of them past ``collector.total_frames`` where the total is not a
    whole number of batches, as TorchRL's collectors round it up.

    ``collector.backend=direct`` steps ``env`` in this process. ``process`` runs
    ``collector.num_workers`` env processes through TorchRL's ``MultiSyncCollector``, and
    ``ray`` as many Ray actors through TorchRL's ``RayCollector`` (see
    :func:`make_ray_collector`). Workers build their own env from the config, run the
    exploration policy on the CPU and collect ``frames_per_batch / num_workers`` frames per
    batch; the batch holds every worker's share, so the learner's update-to-data ratio is
    exact. :func:`push_policy_weights` sends the learner's weights to the workers. Each
    worker records its episode, for the checkpoints
    (:class:`~torchrl_rave.recipe.episode.EpisodeWorkerCollector`).
    """
    total = cfg.collector.total_frames
    grid = min(cfg.collector.frames_per_batch, total)  # the uninterrupted run's batches
    remaining = -(-total // grid) * grid - frames_done
    common = dict(
        frames_per_batch=min(grid, remaining),
        total_frames=remaining,
        init_random_frames=max(0, cfg.collector.init_random_frames - frames_done),
    )
    if cfg.collector.backend == "direct":
        return Collector(
            env,
            policy,
            device=device,
            auto_register_policy_transforms=False,  # our policies keep no recurrent state
            **common,
        )
    workers = cfg.collector.num_workers
    common["frames_per_batch"] -= common["frames_per_batch"] % workers
    cpu = torch.device("cpu")
    if cfg.collector.backend == "ray":
        collector = make_ray_collector(cfg, common)
    else:
        collector = MultiSyncCollector(
            [functools.partial(make_env, cfg, cpu, record_episode=True)] * workers,
            policy,
            device=cpu,  # actors run the exploration policy on the CPU
            storing_device=cpu,
            cat_results="stack",
            # each worker keeps its episode for the checkpoints (recipe.episode)
            collector_class=ProcessWorkerCollector,
            **common,
        )
    # distinct, reproducible streams per worker; a resumed run does not replay old episodes
    collector.set_seed(cfg.env.seed + frames_done)
    push_policy_weights(collector, policy)
    return collector


def worker_policy(cfg: DictConfig):
    """The exploration policy of a Ray collector worker, built on its CPU from the config;
    its weights come from the learner (:func:`push_policy_weights`)."""
    torch.set_num_threads(max(1, int(cfg.ray.worker_cpus)))
    env = make_env(cfg, torch.device("cpu"))
    try:
        return make_actor(cfg, env, ALGORITHMS[cfg.algorithm])[1]
    finally:
        env.close()


class ProcessWorkerCollector(EpisodeWorkerCollector):
    """TorchRL's ``Collector`` as a ``MultiSyncCollector``'s worker process: it keeps its
    episode for the checkpoints
    (:class:`~torchrl_rave.recipe.episode.EpisodeWorkerCollector`) and ignores SIGINT and
    SIGTERM. A Ctrl-C at the terminal, or a batch scheduler's SIGTERM (Slurm's
    ``scancel``), reaches every process of the group; the learner's process answers it (a
    checkpoint after the update under way, then it shuts the workers down), and a worker
    that died of a Ctrl-C left the learner waiting for its answer forever. A worker still
    ends with its learner: it exits within seconds of its learner's death (a SIGKILL), and
    the collector's shutdown kills one that does not answer."""

    def __init__(self, *args, **kwargs) -> None:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, signal.SIG_IGN)
        super().__init__(*args, **kwargs)


class RayWorkerCollector(EpisodeWorkerCollector):
    """TorchRL's ``Collector`` as a Ray actor: it keeps its episode for the checkpoints
    (:class:`~torchrl_rave.recipe.episode.EpisodeWorkerCollector`), seeds its process's
    torch generator with its own seed, and has a one-line repr (Ray prefixes every line a
    worker logs with its actor's repr, which for a ``Collector`` spans the whole env and
    policy)."""

    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        """Seeds the env, as ``Collector.set_seed`` does, then, as TorchRL does for a
        ``MultiSyncCollector``'s worker processes, this actor's torch generator (its
        exploration noise and random actions) and a reset, so that the first step acts
        from the seeded reset. (``RayCollector.set_seed`` did neither: each actor's
        first observation came from its unseeded reset at construction, which its env's
        state no longer matched, and its draws were not reproducible.)"""
        out = super().set_seed(seed, static_seed=static_seed)
        torch.manual_seed(seed)
        self.reset()
        return out

    def __repr__(self) -> str:
        return f"{type(self).__name__}(worker={getattr(self, 'worker_idx', '?')})"


def make_ray_collector(cfg: DictConfig, common: dict):
    """TorchRL's ``RayCollector``: ``collector.num_workers`` Ray actors, each a CPU
    ``Collector`` with its own env and exploration policy, collecting in lockstep.

    With Ray not yet started in this process, ``ray.address=null`` starts a local instance
    (``ray.num_cpus`` CPUs) and ``auto`` or a cluster address joins one. Each actor reserves
    ``ray.worker_cpus`` CPUs, ``ray.worker_memory`` bytes and ``ray.worker_resources``.
    Weights travel by TorchRL's Ray weight-sync scheme. Every node needs torchrl-rave and
    the env's packages installed; this module's factories travel with the actors by value.
    """
    import sys
    import warnings

    import ray
    import ray.cloudpickle
    from torchrl.collectors.distributed import RayCollector

    # the env and policy factories live in this recipe module, which Ray workers cannot
    # import by name: pickle them by value
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    r = cfg.ray
    ray_init = {"num_cpus": r.num_cpus, "include_dashboard": False}
    if r.address is not None and not ray.is_initialized():
        # join the cluster here (a driver connection, dropped when this process exits) so
        # that its resources are checked before any actor waits for them
        reach_ray_address(r.address, cfg.collector.timeout_s or 30.0)
        ray.init(address=r.address)
        check_ray_fits(cfg, ray.cluster_resources(), f"the Ray cluster at {r.address}")
    remote = {"num_cpus": r.worker_cpus, "num_gpus": 0}  # actors explore on the CPU
    if r.worker_memory is not None:
        remote["memory"] = r.worker_memory
    if r.worker_resources:
        remote["resources"] = dict(r.worker_resources)
    cpu = torch.device("cpu")
    with warnings.catch_warnings():
        # the policy comes from a factory; its weights are pushed explicitly
        warnings.filterwarnings("ignore", message="The policy is not an nn.Module")
        return RayCollector(
            [functools.partial(make_env, cfg, cpu, record_episode=True)]
            * cfg.collector.num_workers,
            policy_factory=functools.partial(worker_policy, cfg),
            collector_class=RayWorkerCollector,
            sync=True,  # one share from every worker per batch
            device=cpu,
            storing_device=cpu,
            ray_init_config=ray_init,
            remote_configs=remote,
            collector_kwargs={"auto_register_policy_transforms": False},
            **common,
        )


def push_policy_weights(collector, policy) -> None:
    """Sends ``policy``'s current weights to every collector worker (TorchRL's weight-sync
    schemes; a no-op for the direct backend, which runs ``policy`` itself). Raises
    :class:`CollectorFailure` when a worker process has died since its last batch: the
    push would wait for its answer forever."""
    if isinstance(collector, Collector):
        return
    if isinstance(collector, MultiSyncCollector):
        dead = [(i, p.exitcode) for i, p in enumerate(collector.procs) if not p.is_alive()]
        if dead:
            names = ", ".join(f"{i} (exit code {code})" for i, code in dead)
            raise CollectorFailure(f"worker {names} died after its last batch")
    collector.update_policy_weights_(TensorDict.from_module(policy).data)


def push_or_stop(
    collector, policy, cfg: DictConfig, save_checkpoint: Callable[[], object], frames: int,
    run_dir: str,
) -> None:  # fmt: skip
    """:func:`push_policy_weights` after a batch; when a worker has died since, the state
    after that batch is checkpointed (``save_checkpoint()``), the collector shut down, and
    :class:`CollectorFailure` names the env, the frame and the worker."""
    try:
        push_policy_weights(collector, policy)
    except CollectorFailure as err:
        where = stop_run(collector, save_checkpoint)
        raise CollectorFailure(
            f"a {cfg.collector.backend} collector worker running {cfg.env.name} failed after "
            f"frame {frames}: {err}. The run stopped; {where}: resume with resume={run_dir}"
        ) from None


def workers_share_weights(collector, policy) -> bool:
    """Whether ``collector``'s worker processes act with ``policy``'s own tensors, as a
    ``MultiSyncCollector`` of a CPU policy does (it moves them into shared memory): the
    workers then see every update at once, pushed or not. A GPU policy's workers (and
    Ray's) hold copies, which change only on a push."""
    if not isinstance(collector, MultiSyncCollector):
        return False
    tensors = [*policy.parameters(), *policy.buffers()]
    return bool(tensors) and all(t.is_shared() for t in tensors)


class CollectorFailure(RuntimeError):
    """A collector worker raised or died; the run stopped with a checkpoint."""


class CollectorTimeout(CollectorFailure):
    """No batch came from the collector within ``collector.timeout_s`` (a hung worker)."""


class NonFiniteEnvOutput(RuntimeError):
    """The environment produced NaN, infinite or unusably large observations or rewards."""


# Beyond this magnitude an observation or reward cannot be normalised in float32 (its
# square, the variance, would overflow), so no learner here could use it.
MAX_MAGNITUDE = 1e18


def check_finite(data: TensorDictBase) -> str | None:
    """What is wrong with the first collected entry holding NaN/inf, values beyond
    ``MAX_MAGNITUDE``, or values that are not floating point, with its name; ``None`` when
    all are usable."""
    for key in ("observation", ("next", "observation"), ("next", "reward"), "action"):
        value = data[key]
        if not value.is_floating_point():
            return f"{value.dtype} values (not floating point) in {key!r}"
        if not bool(torch.isfinite(value).all()):
            return f"NaN/inf in {key!r}"
        if key != "action" and bool((value.abs() > MAX_MAGNITUDE).any()):
            top = value.abs().max().item()
            return f"values up to {top:.3g} (beyond ±{MAX_MAGNITUDE:g}) in {key!r}"
    return None


class StopRequest:
    """SIGINT/SIGTERM ask the loop to checkpoint and stop: in the middle of a batch's
    updates after the update or world-model step under way (the rest is owed to the
    resumed run, :func:`~torchrl_rave.recipe.update.update_on_batch`), otherwise at the
    end of the batch; a second signal stops at once."""

    def __init__(self) -> None:
        self.requested = False
        self._previous = {}

    def __enter__(self) -> StopRequest:
        if hasattr(signal, "SIGTERM") and threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame) -> None:
        self.requested = True
        signal.signal(signum, self._previous[signum])

    def __exit__(self, *exc) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def stop_run(collector, save_checkpoint: Callable[[], object]) -> str:
    """Checkpoints the state so far and shuts the collector down, for a run that must stop;
    returns what its error message says of the checkpoint: where it is, or, when writing
    it failed too, why (the run's own error is never hidden behind that failure)."""
    try:
        saved = save_checkpoint()
        if isinstance(saved, list):  # a seed group's, one per seed
            where = f"checkpoints {', '.join(map(str, saved))} hold everything up to that frame"
        else:
            where = f"checkpoint {saved} holds everything up to that frame"
    except Exception as err:  # noqa: BLE001 (the run's own error must not be lost)
        where = f"the checkpoint could not be written ({type(err).__name__}: {err})"
    shutdown_quietly(collector)
    return where


def shutdown_quietly(collector) -> None:
    """Shuts ``collector`` down (again: TorchRL's shutdowns are idempotent); a failure,
    e.g. of a dead worker, is logged rather than raised over the run's own error."""
    try:
        collector.shutdown()
    except Exception:  # noqa: BLE001 (a dead worker may fail the shutdown too)
        logging.getLogger(__name__).warning("collector shutdown failed", exc_info=True)


@contextlib.contextmanager
def shutdown_on_error(get_collector: Callable[[], object]) -> Iterator[None]:
    """Shuts the collector (``get_collector()``, possibly ``None``) down when the block
    raises, e.g. because a checkpoint could not be written, so that no worker outlives it."""
    try:
        yield
    except BaseException:
        collector = get_collector()
        if collector is not None:
            shutdown_quietly(collector)
        raise


_STOP_GRACE_S = 1.0  # how long an alarm due during a stop waits for the SIGCONT


@contextlib.contextmanager
def deadline(seconds: float | None, message: str) -> Iterator[None]:
    """Raises :class:`CollectorTimeout` (``message``) in the block if it runs longer than
    ``seconds`` (``None``: no limit). It uses ``SIGALRM``, so it only works in the main
    thread on POSIX; elsewhere the block runs without a limit.

    A process that was stopped (``SIGSTOP``, ``kill -STOP``, Ctrl-Z) is not hung: on
    ``SIGCONT`` the wait starts afresh. An alarm that fell due while the process was
    stopped is delivered together with the ``SIGCONT``, before it, so an expiring alarm
    first waits a short grace period for a ``SIGCONT`` before it raises."""
    usable = hasattr(signal, "setitimer") and threading.current_thread() is threading.main_thread()
    if not seconds or not usable:
        yield
        return
    expiring = False

    def expire(signum, frame):
        nonlocal expiring
        if not expiring:
            expiring = True
            signal.setitimer(signal.ITIMER_REAL, _STOP_GRACE_S)
            return
        raise CollectorTimeout(message)

    def resumed(signum, frame):
        nonlocal expiring
        expiring = False
        signal.setitimer(signal.ITIMER_REAL, float(seconds))

    previous = signal.signal(signal.SIGALRM, expire)
    previous_cont = signal.signal(signal.SIGCONT, resumed)
    signal.setitimer(signal.ITIMER_REAL, float(seconds))
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
        signal.signal(signal.SIGCONT, previous_cont)


def guarded_batches(
    collector,
    cfg: DictConfig,
    save_checkpoint: Callable[[], object],
    frames: Callable[[], int],
    run_dir: str,
) -> Iterator[TensorDictBase]:
    """The collector's batches. A worker that raises or dies stops the run cleanly: the
    state after the last complete batch is checkpointed (``save_checkpoint()``), the
    collector is shut down and :class:`CollectorFailure` names the env, the frame and the
    cause. (With the direct backend the env's own error propagates.) A batch that takes
    longer than ``collector.timeout_s`` seconds (a worker hung rather than crashed) stops
    the run the same way with :class:`CollectorTimeout`, whatever the backend."""
    iterator = iter(collector)
    timeout = cfg.collector.get("timeout_s")
    while True:
        try:
            hung = (
                f"no batch came from the {cfg.collector.backend} collector running "
                f"{cfg.env.name} within collector.timeout_s={timeout:g} s after frame "
                f"{frames()}: a worker hung"
            )
            with deadline(timeout, hung):
                data = next(iterator)
        except StopIteration:
            return
        except CollectorTimeout as err:
            where = stop_run(collector, save_checkpoint)
            raise CollectorTimeout(
                f"{err}. The run stopped; {where}: resume with resume={run_dir}"
            ) from None
        except Exception as err:
            if cfg.collector.backend == "direct":
                raise
            where = stop_run(collector, save_checkpoint)
            traceback_at = (
                " (a worker that raised printed its traceback to stderr)"
                if cfg.collector.backend == "process"
                else ""
            )
            raise CollectorFailure(
                f"a {cfg.collector.backend} collector worker running {cfg.env.name} failed "
                f"after frame {frames()}: {type(err).__name__}: {err}{traceback_at}. The run "
                f"stopped; {where}: resume with resume={run_dir}"
            ) from err
        yield data
