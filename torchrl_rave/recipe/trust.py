"""The trust boundary of a run directory: what its saved config may decide.

A run directory can come from anyone. Loading it (:func:`~torchrl_rave.recipe.load_policy`,
:func:`~torchrl_rave.recipe.load_agent`, ``resume=``) reads tensors and JSON only, and the
saved config decides the sizes and hyper-parameters it was trained with. It does not decide
what this process imports, connects to, or opens by name. Those values are taken from a
saved config only when the caller passes them again (``resume=<dir> env.name=<value>`` on
the command line) or says it trusts the directory (``load_policy(run_dir, trust=True)``):

- ``env.name`` of the form ``module:EnvId``, which imports ``module`` (gymnasium's
  convention; from the working directory first, where a run directory may ship one);
- ``ray.address``, which joins that Ray cluster;
- any string in ``env.kwargs``, which the env may open as a file (MuJoCo's ``xml_file``) or
  resolve as a name;
- ``logger.backend=wandb``, which logs in to W&B and writes to the project (and, on
  resume, continues the W&B run) that the directory names;

A saved config is data: an interpolation in it (``${...}``), which OmegaConf would resolve
by reading this process's environment variables or calling a resolver, is refused
whatever the trust (:func:`check_plain_data`); torchrl-rave saves configs resolved, so only
an edited directory holds one.
"""

from __future__ import annotations

import argparse
import socket

from omegaconf import DictConfig, OmegaConf

from torchrl_rave.recipe.config import ConfigError

__all__ = [
    "UntrustedRunConfig",
    "add_trust_flag",
    "check_plain_data",
    "check_trusted",
    "outside_references",
    "reach_ray_address",
]


class UntrustedRunConfig(ConfigError):
    """A saved config names a module, an address or a file, and the caller did not pass
    that value itself nor say that it trusts the run directory."""


def outside_references(cfg: DictConfig) -> dict[str, tuple[object, str]]:
    """The values of ``cfg`` that would make this process import, connect to or open
    something by name: ``{key: (value, what it would do)}``."""
    # read as plain data: accessing a DictConfig's value would resolve an interpolation
    data = OmegaConf.to_container(cfg, resolve=False) if OmegaConf.is_config(cfg) else cfg
    found: dict[str, tuple[object, str]] = {}
    env = data.get("env") or {}
    name = str(env.get("name"))
    if ":" in name:
        found["env.name"] = (name, f"imports the module {name.split(':', 1)[0]!r}")
    address = (data.get("ray") or {}).get("address")
    if address is not None:
        found["ray.address"] = (address, "joins that Ray cluster")
    for key, value in (env.get("kwargs") or {}).items():
        if isinstance(value, str):
            found[f"env.kwargs.{key}"] = (
                value,
                "is passed to the env, which may open it as a file",
            )
    curriculum = data.get("curriculum") or {}
    if curriculum.get("kwarg") is not None:  # each stage's value becomes an env keyword
        stages = curriculum.get("stages") or []
        if any(isinstance(v, str) for v in stages):
            found["curriculum.stages"] = (
                list(stages),
                "passes strings to the env as a keyword, which it may open as files",
            )
    logger = data.get("logger") or {}
    if logger.get("backend") == "wandb":
        found["logger.backend"] = (
            "wandb",
            f"logs in to W&B and writes to its project {logger.get('project')!r} (a resumed "
            "run continues the W&B run its checkpoint names)",
        )
    return found


def check_plain_data(data: dict, given: set[str], where: str) -> None:
    """Raises :class:`UntrustedRunConfig` naming each string of a saved config ``data``
    (nested dicts and lists) that OmegaConf would resolve as an interpolation, unless its
    key (or a parent key) is in ``given`` (the caller passes the value itself)."""
    problems = [
        f"{where}: its saved config sets {key}={value!r}, an interpolation, which would be "
        "resolved here (reading this process's environment variables or calling a "
        "resolver); a saved config is data and torchrl-rave saves it resolved, so the run "
        "directory was edited. Pass the key on the command line with the value to use"
        for key, value in _interpolations(data)
        if not {".".join(key.split(".")[:n]) for n in range(1, key.count(".") + 2)} & given
    ]
    if problems:
        raise UntrustedRunConfig(problems)


def _interpolations(data: object, prefix: str = ""):
    """``(key, value)`` of every string of ``data`` that holds ``${``."""
    if isinstance(data, dict):
        for key, value in data.items():
            yield from _interpolations(value, f"{prefix}{key}.")
    elif isinstance(data, list):
        for index, value in enumerate(data):
            yield from _interpolations(value, f"{prefix}{index}.")
    elif isinstance(data, str) and "${" in data:
        yield prefix[:-1], data


def check_trusted(saved: DictConfig, given: set[str], where: str, how: str) -> None:
    """Raises :class:`UntrustedRunConfig` for each value of ``saved`` that
    :func:`outside_references` names and whose key (or a parent key) is not in ``given``;
    ``how`` tells the caller how to pass one."""
    problems = []
    for key, (value, effect) in outside_references(saved).items():
        parents = {".".join(key.split(".")[:n]) for n in range(1, key.count(".") + 2)}
        if parents & given:
            continue
        problems.append(
            f"{where}: its saved config sets {key}={value!r}, which {effect}; a run directory "
            f"does not decide that. {how}"
        )
    if problems:
        raise UntrustedRunConfig(problems)


HTTP2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n"


def reach_ray_address(address: str, timeout_s: float) -> None:
    """Raises ``ConnectionError`` naming ``address`` when no Ray cluster answers there
    within ``timeout_s``: nothing accepts a TCP connection on its port, or what does is
    not a gRPC server (Ray's GCS is one; it answers HTTP/2's preface with a SETTINGS
    frame). ``ray.init`` itself retries an unreachable address for minutes, hangs on a
    port where something else listens, and ignores SIGTERM meanwhile. ``auto`` (a
    cluster on this machine, found by Ray) is not checked."""
    if address == "auto":
        return
    hostport = address.split("://", 1)[-1].rstrip("/")
    host, _, port = hostport.rpartition(":")
    if not host or not port.isdigit():
        raise ConnectionError(f"ray.address={address!r} is not of the form host:port or auto")
    try:
        conn = socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s)
    except OSError as err:
        raise ConnectionError(
            f"no Ray cluster answers at ray.address={address!r} ({err.strerror or err}) "
            f"within {timeout_s:g} s; check the address, or start the cluster"
        ) from None
    header = b""
    with conn:
        # Ray's GCS is a gRPC server: to HTTP/2's client preface it answers with a
        # SETTINGS frame (a 9-byte header whose 4th byte, the frame type, is 4)
        try:
            conn.sendall(HTTP2_PREFACE + b"\x00\x00\x00\x04\x00\x00\x00\x00\x00")
            while len(header) < 9:
                chunk = conn.recv(9 - len(header))
                if not chunk:
                    break
                header += chunk
        except OSError:  # silent past the timeout, or it hung up: not a Ray cluster
            pass
    if len(header) < 9 or header[3] != 4:
        raise ConnectionError(
            f"something listens at ray.address={address!r} but does not answer as a Ray "
            "cluster does (a gRPC server); check the address (the head node's GCS port, "
            "6379 by default)"
        )


def add_trust_flag(parser: argparse.ArgumentParser) -> None:
    """The ``--trust`` flag of a script that reads run directories: with it, their saved
    ``env.name`` may import a module and their ``env.kwargs`` be opened."""
    parser.add_argument(
        "--trust",
        action="store_true",
        help="the run directories are trusted: their saved env.name may import a module and "
        "their env.kwargs be opened (torchrl_rave.recipe.trust)",
    )
