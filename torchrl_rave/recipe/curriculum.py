"""The recipe's ``curriculum`` keys: an env keyword that steps through stages as an
evaluation metric passes thresholds (:class:`~torchrl_rave.trainers.Curriculum`)."""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

from torchrl_rave.trainers.curriculum import Curriculum

__all__ = ["make_curriculum", "stage_config"]


def make_curriculum(cfg: DictConfig) -> Curriculum | None:
    """The curriculum of ``curriculum.kwarg``, or ``None`` when it is unset."""
    c = cfg.get("curriculum")
    if c is None or c.kwarg is None:
        return None
    values = OmegaConf.to_container(c.stages) if OmegaConf.is_config(c.stages) else c.stages
    return Curriculum(values, list(c.thresholds or []), metric=c.metric)


def stage_config(cfg: DictConfig, curriculum: Curriculum) -> DictConfig:
    """``cfg`` with ``env.kwargs[curriculum.kwarg]`` set to the current stage's value: the
    config the stage's envs (and collector workers) are built from."""
    staged = cfg.copy()
    kwargs = OmegaConf.to_container(staged.env.kwargs) if staged.env.kwargs is not None else {}
    kwargs[cfg.curriculum.kwarg] = curriculum.value
    OmegaConf.set_struct(staged, False)
    staged.env.kwargs = kwargs
    OmegaConf.set_struct(staged, OmegaConf.is_struct(cfg))
    return staged
