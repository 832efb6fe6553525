"""Say which torch this environment has, and fail when it is not the build that was asked for.

The Docker build runs it right after `pip install` (``python scripts/check_torch.py cpu``): pip
only *warns* when the CPU wheel index cannot be reached and then installs PyPI's CUDA build of
the pinned version with several GB of nvidia-* wheels, so a silent 2 GB-larger image is caught
here, at build time, with the reason. ``cuda`` checks the other way (a learner image for a GPU).
"""

from __future__ import annotations

import importlib.metadata as md
import sys

VARIANTS = ("cpu", "cuda")


def nvidia_wheels() -> list[str]:
    """Installed distributions that are CUDA runtime wheels (nvidia-cublas-cu12, ...)."""
    names = {(d.metadata["Name"] or "").lower() for d in md.distributions()}
    return sorted(n for n in names if n.startswith("nvidia-") or n == "triton")


def check(variant: str) -> tuple[bool, str]:
    """(ok, one line about the torch that is installed) for the wanted ``variant``."""
    if variant not in VARIANTS:
        return False, f"unknown torch variant {variant!r}: use one of {', '.join(VARIANTS)}"
    import torch

    cuda = torch.version.cuda
    extra = nvidia_wheels()
    line = (f"torch {torch.__version__}: {'CUDA ' + cuda if cuda else 'CPU-only'} build"
            + (f", with {len(extra)} CUDA wheels ({', '.join(extra[:3])}{', ...' if len(extra) > 3 else ''})"
               if extra else ""))
    if variant == "cpu" and (cuda or extra):
        return False, (line + ". The CPU build was asked for: the CPU wheel index was probably not "
                       "reachable and pip fell back to PyPI's CUDA build (pass --build-arg "
                       "TORCH_INDEX=<a reachable index with the +cpu wheel>, or --build-arg TORCH=cuda "
                       "if the CUDA build is what you want)")
    if variant == "cuda" and not cuda:
        return False, line + ". The CUDA build was asked for but this torch has no CUDA"
    return True, line


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    ok, line = check(args[0] if args else "cpu")
    print(("ok: " if ok else "ERROR: ") + line, file=sys.stdout if ok else sys.stderr)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
