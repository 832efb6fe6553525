"""Named training recipes (``learner.recipe``) and the one function that turns a configuration into
SAC's hyper-parameters: the learner, the actors (n-step horizon, discount, critic inputs) and
``forcegrasp train`` all read them here. Why the default is what it is: ``docs/recipe.md``."""

from __future__ import annotations

import dataclasses

from forcegrasp.sac_config import SACConfig, check_value


#: Named presets of SACConfig fields (``learner.recipe``); [learner.sac] overrides go on top.
#: "paper": the paper's settings (one update per environment step, a critic that sees what the
#: actor sees). "fast": the recipe of docs/recipe.md, measured on this project's 2-core machines:
#: a quarter update per step, the asymmetric critic, critic LayerNorm (with the demonstrations
#: of `OBJECT_DEMOS`), and observation normalisation, without which the noisy torques of the
#: default randomisation (``env.torque_noise_range``) drown the proprioceptive inputs.
RECIPES: dict[str, dict] = {
    "paper": {},
    "fast": {"updates_per_step": 0.25, "privileged_critic": True, "critic_layer_norm": True, "obs_norm": True},
}

#: Per-object settings on top of a recipe, under the [learner.sac] overrides: for a lever that helps
#: one object and costs another (none at present).
OBJECT_RECIPES: dict[str, dict[str, dict]] = {"fast": {}}


def recipe_settings(recipe: str, object_name: str) -> dict:
    """The SACConfig fields that recipe sets on that object (before any [learner.sac] override)."""
    return {**RECIPES[recipe], **OBJECT_RECIPES.get(recipe, {}).get(object_name, {})}


#: Scripted demonstrations per env, for ``actor.demo_episodes = -1`` (the default): every object's,
#: an imported one's too. The mug's grasp was never found in 30 minutes without them; with critic
#: LayerNorm they keep the entropy temperature from collapsing before the first success (the spray
#: bottle) (docs/recipe.md). `OBJECT_DEMOS` holds an object that needs another number (none at present).
DEMOS_PER_ENV = 4
OBJECT_DEMOS: dict[str, int] = {}


def demo_episodes(object_name: str, configured: int) -> int:
    """Demonstrations per env that ``actor.demo_episodes = configured`` means for this object
    (a negative number: the object's entry in `OBJECT_DEMOS`, else `DEMOS_PER_ENV`)."""
    return OBJECT_DEMOS.get(object_name, DEMOS_PER_ENV) if configured < 0 else int(configured)


def sac_config(config) -> SACConfig:
    """SACConfig with a `forcegrasp.config.Config`'s recipe (for its object), its [learner.sac] overrides and its run seed; unknown
    or ill-typed keys are a ConfigError. The learner and the actors (n-step horizon, discount, critic
    inputs) read SAC settings through this one function."""
    from forcegrasp.config import ConfigError

    known = {f.name: f for f in dataclasses.fields(SACConfig)}
    overrides = {}
    for key, value in config.learner.sac.items():
        if key not in known:
            raise ConfigError(f"learner.sac.{key}: unknown SAC setting; known: {', '.join(sorted(known))}")
        try:
            overrides[key] = check_value(key, value)
        except ValueError as exc:
            raise ConfigError(f"learner.sac.{exc}") from None
    recipe = recipe_settings(config.learner.recipe, config.env.object)
    try:
        return dataclasses.replace(SACConfig(seed=config.run.seed), **{**recipe, **overrides})
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"learner.sac: {exc}") from None
