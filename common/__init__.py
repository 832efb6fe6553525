"""ForceGrasp: force-feedback functional grasping with distributed SAC."""

import os
from pathlib import Path

# Offscreen rendering must pick its GL backend before mujoco is first imported anywhere.
os.environ.setdefault("MUJOCO_GL", "egl")

__version__ = "0.1.0"

#: Asset folder (objects, grasp labels): the repository's, or FORCEGRASP_ASSETS for a user's own set.
ASSETS_DIR = Path(os.environ.get("FORCEGRASP_ASSETS") or Path(__file__).resolve().parent.parent / "assets")


def _register_envs() -> None:
    """Gymnasium ids FunctionalGrasp-<Object>-v0; kwargs pass through to FunctionalGraspEnv."""
    from gymnasium.envs.registration import register, registry

    for object_name, env_name in (
        ("spray_bottle", "SprayBottle"),
        ("power_drill", "PowerDrill"),
        ("mug", "Mug"),
        ("camera", "Camera"),
    ):
        env_id = f"FunctionalGrasp-{env_name}-v0"
        if env_id not in registry:
            register(id=env_id, entry_point="forcegrasp.env:FunctionalGraspEnv", kwargs={"object_name": object_name})


_register_envs()
