"""The actor role: several FunctionalGrasp envs stepped with one copy of the policy, their
transitions packed into batches for the learner. No network: the actor service sends the batches
over Zenoh and feeds it the learner's broadcasts; ``forcegrasp train`` hands them to a learner in
the same process.

- With ``env.objects`` its envs step several objects (`forcegrasp.multi_object.assign_objects`: env
  ``j`` of actor ``i`` steps ``objects[(i * envs_per_actor + j) % len(objects)]``); every transition
  and ended episode carries its object's index into the batch's ``objects`` names (statistics only).
  With ``env.object_sampling = "adaptive"`` that is each env's first object; later episodes draw
  theirs from `forcegrasp.multi_object.AdaptiveObjectSampler` (an env slot keeps one env per object).
- With ``actor.demo_episodes`` (default: the recipe's number for the object,
  `forcegrasp.recipes.DEMOS_PER_ENV`) each env first plays that many episodes of the scripted approach
  (`forcegrasp.scripted`) *told the true object offset*: demonstrations that put the success
  bonus into the replay buffer from the start (prior data, as in RLPD). The offset is simulator
  knowledge the deployed policy never sees; the demonstrations are counted apart from the
  policy's own episodes (``demo_episodes`` in :meth:`stats`, not in the online success).
- Otherwise acts uniformly at random for its first ``actor.random_steps`` env steps (and until it
  has weights), then samples from its policy; one batched forward pass serves all its envs.
- Finished episodes reset at once; the transition keeps the true last observation, with
  ``terminated`` marking real terminal states.
- With ``env.curriculum_success`` its envs start at the fixed training conditions and the
  randomisation ranges open as its policy episodes succeed (`forcegrasp.curriculum`).
- With the learner's ``n_step`` > 1 transitions leave through per-env n-step accumulators, with
  ``privileged_critic`` they carry the simulator state the critic sees (read from the same
  configuration as the learner).
"""

from __future__ import annotations

import logging

import numpy as np

from forcegrasp import task
from forcegrasp.config import Config
from forcegrasp.curriculum import RandomisationCurriculum
from forcegrasp.nstep import NStepAccumulator
from forcegrasp.policy import Policy
from forcegrasp.policy_file import PolicyMetadata
from forcegrasp.protocol import TransitionBatch
from forcegrasp.multi_object import AdaptiveObjectSampler, actor_index, assign_objects, run_objects
from forcegrasp.runtime import make_env
from forcegrasp.recipes import demo_episodes, sac_config
from forcegrasp.scripted import ScriptedApproach


class Actor:
    """Selects actions, observes what the envs return, takes new weights (:meth:`update`)."""

    def __init__(self, config: Config, actor_id: str, seed: int | None = None):
        self.config = config
        self.actor_id = actor_id
        n = config.actor.envs_per_actor
        self.objects = run_objects(config.env)  # the batch's object names; env i steps env_objects[i]
        self.env_objects = assign_objects(self.objects, n, actor_index(actor_id))
        self._object_ix = np.array([self.objects.index(o) for o in self.env_objects], np.uint8)
        self.envs = [make_env(config, o) for o in self.env_objects]
        self._pool = [{o: env} for o, env in zip(self.env_objects, self.envs)]  # slot i's env of each object
        e = config.env
        self.curriculum = (RandomisationCurriculum(e.curriculum_success, e.curriculum_window, e.curriculum_stages)
                           if e.curriculum_success else None)
        self._set_level()
        if len(set(self.env_objects)) < len(self.objects):  # fine if other actors step the rest
            logging.getLogger("forcegrasp.actor").warning(
                "actor %s: %d envs step %s of the %d objects %s", actor_id, n,
                ", ".join(dict.fromkeys(self.env_objects)), len(self.objects), ", ".join(self.objects))
        base_seed = config.run.seed + 1000 if seed is None else seed
        self.rng = np.random.default_rng(base_seed)
        adaptive = config.env.object_sampling == "adaptive" and len(self.objects) > 1
        self.sampler = AdaptiveObjectSampler(self.objects, np.random.default_rng([base_seed, 1])) if adaptive else None
        self.obs = np.stack([env.reset(seed=base_seed + i)[0] for i, env in enumerate(self.envs)])
        self.obs_dim, self.act_dim = self.obs.shape[1], task.ACT_DIM
        sac = sac_config(config)  # the learner's n-step horizon, discount and critic inputs
        self.privileged = bool(sac.privileged_critic)
        self.priv = np.stack([env.privileged_state() for env in self.envs]) if self.privileged else None
        self.nstep = [NStepAccumulator(sac.n_step, sac.gamma) for _ in self.envs]
        self.policy: Policy | None = None
        self.policy_version = 0
        self.steps = 0
        self.episodes = 0
        self.successes = 0
        self._pending: list = []
        self._pending_objects: list[int] = []  # the object index of each pending transition
        self._ended: list[tuple[float, int, bool, int]] = []
        self.by_object = {o: {"episodes": 0, "successes": 0} for o in self.objects}
        self._returns = np.zeros(n)
        self._lengths = np.zeros(n, dtype=np.int64)
        self._demos_left = [demo_episodes(o, config.actor.demo_episodes) for o in self.env_objects]
        self._demo = [self._new_demo(i) for i in range(n)]
        self.demo_episodes = self.demo_successes = 0

    def _set_level(self) -> None:
        """Every env draws its next episode's conditions at the curriculum's level."""
        if self.curriculum is not None:
            for env in (env for pool in self._pool for env in pool.values()):
                env.randomisation_level = self.curriculum.level

    def _new_demo(self, i: int) -> ScriptedApproach | None:
        """The scripted approach for env `i`'s new episode while it still owes demonstrations."""
        if self._demos_left[i] <= 0:
            return None
        env = self.envs[i]
        return ScriptedApproach(env, believed_offset=env.offset)

    def _switch(self, i: int, name: str):
        """Env slot ``i`` now steps ``name``: its env of that object, built (and seeded from the
        actor's stream) on first use."""
        if name not in self._pool[i]:
            env = make_env(self.config, name)
            env.reset(seed=int(self.rng.integers(2**31)))
            if self.curriculum is not None:
                env.randomisation_level = self.curriculum.level
            self._pool[i][name] = env
        self.envs[i], self.env_objects[i] = self._pool[i][name], name
        self._object_ix[i] = self.objects.index(name)
        return self.envs[i]

    def update(self, params: dict[str, np.ndarray], meta: PolicyMetadata, version: int) -> bool:
        """Swap in a newer policy; False for one older than ours. Raises ValueError for a policy
        of another shape than this actor's envs, or one trained with other action step sizes or
        proprioception (an actor started with another configuration would otherwise act, and send
        transitions, at the wrong scale or on observations that mean something else)."""
        if meta.obs_dim != self.obs_dim or meta.act_dim != self.act_dim:
            raise ValueError(f"policy is {meta.obs_dim}->{meta.act_dim}, env is {self.obs_dim}->{self.act_dim}")
        if task.proprioception_of(meta) != self.config.env.proprioception:  # same sizes, other meaning
            raise ValueError(f"policy observes {task.proprioception_of(meta)} proprioception, "
                             f"the envs {self.config.env.proprioception}")
        task.check_action_steps(meta, self.config.env.action_steps())  # the sizes make_env gave the envs
        if version <= self.policy_version and self.policy is not None:
            return False  # an older broadcast overtaken by a query reply, say
        self.policy = Policy.from_weights(params, meta, seed=int(self.rng.integers(2**31)))
        self.policy_version = version
        return True

    def act(self) -> np.ndarray:
        if self.steps < self.config.actor.random_steps or self.policy is None:
            actions = self.rng.uniform(-1.0, 1.0, (len(self.envs), self.act_dim)).astype(np.float32)
        else:
            actions = self.policy(self.obs, deterministic=False).astype(np.float32)
        noise = self.config.actor.demo_noise
        for i, demo in enumerate(self._demo):
            if demo is not None:
                a = demo() + (self.rng.normal(0.0, noise, self.act_dim) if noise > 0 else 0.0)
                actions[i] = np.clip(a, -1.0, 1.0)
        return actions

    def step(self) -> TransitionBatch | None:
        """One step of every env; returns a batch once ``actor.publish_batch`` transitions wait."""
        actions = self.act()
        for i, env in enumerate(self.envs):
            next_obs, reward, terminated, truncated, info = env.step(actions[i])
            next_priv = env.privileged_state() if self.privileged else None
            priv = self.priv[i].copy() if self.privileged else None
            out = self.nstep[i].push(self.obs[i].copy(), actions[i], reward, next_obs, terminated, truncated, priv,
                                     next_priv)
            self._pending.extend(out)
            self._pending_objects.extend([self._object_ix[i]] * len(out))
            self._returns[i] += reward
            self._lengths[i] += 1
            if terminated or truncated:
                if self._demo[i] is not None:
                    self._demos_left[i] -= 1
                    self.demo_episodes += 1
                    self.demo_successes += bool(info["success"])
                else:
                    self._ended.append((self._returns[i], int(self._lengths[i]), bool(info["success"]),
                                        int(self._object_ix[i])))
                    self.episodes += 1
                    self.successes += bool(info["success"])
                    self.by_object[self.env_objects[i]]["episodes"] += 1
                    self.by_object[self.env_objects[i]]["successes"] += bool(info["success"])
                    if self.curriculum is not None and self.curriculum.record(info["success"]):
                        self._set_level()
                    if self.sampler is not None:
                        self.sampler.record(self.env_objects[i], info["success"])
                if self.sampler is not None and self._demos_left[i] <= 0:
                    env = self._switch(i, self.sampler.draw())
                self._returns[i], self._lengths[i] = 0.0, 0
                next_obs, _ = env.reset()
                self._demo[i] = self._new_demo(i)
                if self.privileged:
                    next_priv = env.privileged_state()
            self.obs[i] = next_obs
            if self.privileged:
                self.priv[i] = next_priv
        self.steps += len(self.envs)
        if len(self._pending) >= self.config.actor.publish_batch:
            return self._package()
        return None

    def _package(self) -> TransitionBatch:
        """The waiting transitions and ended episodes as one batch (``seq``/``epoch`` are the
        sender's to set)."""
        p = self._pending
        obs, action, next_obs = (np.array([getattr(t, k) for t in p]) for k in ("obs", "action", "next_obs"))
        reward, term, trunc = (np.array([getattr(t, k) for t in p]) for k in ("reward", "terminated", "truncated"))
        extras = {}
        if any(t.horizon != 1 for t in p):
            extras["horizon"] = np.array([t.horizon for t in p], np.int32)
        if self.privileged:
            extras["privileged"] = np.array([t.extra for t in p], np.float32)
            extras["next_privileged"] = np.array([t.next_extra for t in p], np.float32)
        if self._ended:
            r, n, s, o = zip(*self._ended)
            extras.update(episode_returns=np.array(r, np.float32), episode_lengths=np.array(n, np.int32),
                          episode_successes=np.array(s, bool), episode_objects=np.array(o, np.uint8))
        objects = np.array(self._pending_objects, np.uint8)
        self._pending, self._pending_objects, self._ended = [], [], []
        return TransitionBatch(actor_id=self.actor_id, seq=0, policy_version=self.policy_version, obs=obs,
                               action=action, reward=reward, next_obs=next_obs, terminated=term, truncated=trunc,
                               objects=list(self.objects), object_index=objects, **extras)

    def stats(self) -> dict:
        return {"steps": self.steps, "episodes": self.episodes, "successes": self.successes,
                "demo_episodes": self.demo_episodes,
                "demo_successes": self.demo_successes, "policy_version": self.policy_version,
                **({"curriculum_level": self.curriculum.level} if self.curriculum is not None else {}),
                **({"objects": {o: dict(v) for o, v in self.by_object.items()}} if len(self.objects) > 1 else {})}

    def close(self) -> None:
        for env in (env for pool in self._pool for env in pool.values()):
            env.close()
