"""``forcegrasp export FILE --onnx OUT.onnx``: export a policy file to ONNX (see forcegrasp.export).

The model maps ``observation`` float32 [batch, obs_dim] to ``action`` float32 [batch, 7], the
deterministic action `Policy` returns (in [-1, 1], what the env's step takes); ``--scale-actions``
bakes in the metadata's action range instead. Bad input exits with code 2 and writes nothing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="forcegrasp export", description=__doc__.splitlines()[0])
    parser.add_argument("policy", type=Path, help="policy file (.safetensors), e.g. assets/policies/mug-ff-s0.safetensors")
    parser.add_argument("--onnx", type=Path, required=True, help="output path of the ONNX model (its folder must exist)")
    parser.add_argument("--scale-actions", action="store_true",
                        help="output action_low..action_high units (Policy.rescale) instead of [-1, 1]")
    args = parser.parse_args(argv)

    from forcegrasp.export import export_policy
    from forcegrasp.policy_file import PolicyFileError

    try:
        out = export_policy(args.policy, args.onnx, scale_actions=args.scale_actions)
    except PolicyFileError as exc:  # corrupt or not a policy file; its message names the file or the field
        message = str(exc)
        print(f"error: {message if str(args.policy) in message else f'{args.policy}: {message}'}", file=sys.stderr)
        return 2
    except OSError as exc:  # no such file, no output folder, a folder where a file belongs, permissions
        print(f"error: {exc.filename}: {exc.strerror}" if exc.filename and exc.strerror else f"error: {exc}",
              file=sys.stderr)
        return 2
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
