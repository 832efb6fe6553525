"""ForceGrasp: force-feedback functional grasping with distributed SAC."""

import os
import sys
from importlib import resources
from pathlib import Path

# Offscreen rendering must pick its GL backend before mujoco is first imported anywhere.
os.environ.setdefault("MUJOCO_GL", "egl")

__version__ = "0.1.0"

#: Asset folder (objects, grasp labels, shipped policies): the package's own (the repository's assets/,
#: package data in a wheel), or FORCEGRASP_ASSETS for a user's own set.
ASSETS_DIR = Path(os.environ.get("FORCEGRASP_ASSETS") or str(resources.files(__name__) / "assets"))


def docs_dir() -> Path:
    """Where generated pages and pictures go: the docs/ beside the asset folder (a checkout's, or a
    FORCEGRASP_ASSETS set's); an installed package's own assets are no place to write, so ./docs."""
    beside = ASSETS_DIR.resolve().parent / "docs"
    return beside if beside.is_dir() or os.environ.get("FORCEGRASP_ASSETS") else Path.cwd() / "docs"


# Gymnasium ids (FunctionalGrasp-<Object>-v0) are registered by `forcegrasp.env` when it is
# imported, and here when gymnasium already is: `import gymnasium; import forcegrasp` then
# `gymnasium.make("FunctionalGrasp-Mug-v0")` works, while a client that only speaks the protocol
# (`forcegrasp.protocol`, `forcegrasp.policy`, `forcegrasp.task`) loads neither gymnasium nor mujoco.
if "gymnasium" in sys.modules:
    from forcegrasp import env as _env  # noqa: E402,F401  (registers the ids)
