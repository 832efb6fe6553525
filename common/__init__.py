"""ForceGrasp: force-feedback functional grasping with distributed SAC."""

from pathlib import Path

__version__ = "0.1.0"

#: Repository asset folder (objects, grasp labels). Overridable for installed copies.
ASSETS_DIR = Path(__file__).resolve().parent.parent / "assets"
