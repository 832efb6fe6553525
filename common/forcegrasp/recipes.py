"""Named training recipes (``learner.recipe``) and the one function that turns a configuration into
SAC's hyper-parameters: the learner, the actors (n-step horizon, discount, critic inputs) and
``forcegrasp train`` all read them here. Why the default is what it is: ``docs/recipe.md``."""

from __future__ import annotations

import dataclasses

from forcegrasp.sac import SACConfig


#: Named presets of SACConfig fields (``learner.recipe``); [learner.sac] overrides go on top.
#: "paper": the paper's settings (one update per environment step, a critic that sees what the
#: actor sees). "fast": the recipe of docs/recipe.md, measured on this project's 2-core machines.
RECIPES: dict[str, dict] = {
    "paper": {},
    "fast": {"updates_per_step": 0.25, "privileged_critic": True},
}


#: Scripted demonstrations per env by object, for ``actor.demo_episodes = -1`` (the default). The
#: mug's grasp was never found in 30 minutes without them and by 20 minutes with 4 (two seeds);
#: the camera learned no faster with them (docs/recipe.md), so other objects get none.
OBJECT_DEMOS: dict[str, int] = {"mug": 4}


def demo_episodes(object_name: str, configured: int) -> int:
    """Demonstrations per env that ``actor.demo_episodes = configured`` means for this object."""
    return OBJECT_DEMOS.get(object_name, 0) if configured < 0 else int(configured)


def sac_config(config) -> SACConfig:
    """SACConfig with a `forcegrasp.config.Config`'s recipe, its [learner.sac] overrides and its run seed; unknown
    or ill-typed keys are a ConfigError. The learner and the actors (n-step horizon, discount, critic
    inputs) read SAC settings through this one function."""
    from forcegrasp.config import ConfigError

    known = {f.name: f for f in dataclasses.fields(SACConfig)}
    overrides = {}
    for key, value in config.learner.sac.items():
        if key not in known:
            raise ConfigError(f"learner.sac.{key}: unknown SAC setting; known: {', '.join(sorted(known))}")
        overrides[key] = tuple(value) if isinstance(value, list) else value
    recipe = RECIPES[config.learner.recipe]
    try:
        return dataclasses.replace(SACConfig(seed=config.run.seed), **{**recipe, **overrides})
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"learner.sac: {exc}") from None
