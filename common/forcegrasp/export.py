"""Export a deployed policy to ONNX, so it runs without ForceGrasp, torch or MuJoCo (e.g. onnxruntime).

The graph is built directly from the policy file's numpy weights with ``onnx.helper`` (no
``torch.onnx``, which needs extra packages); it computes what ``Policy(obs)`` returns, the
deterministic action:

* input ``"observation"``: float32 ``[batch, obs_dim]`` (batch dynamic; obs_dim 77 with force
  feedback, 53 without; the order is the metadata's ``obs_layout``);
* output ``"action"``: float32 ``[batch, act_dim]`` (act_dim 7), ``tanh(mean)`` in [-1, 1]: the
  units `FunctionalGraspEnv.step` takes (it multiplies by the step sizes itself). With
  ``scale_actions=True`` (``--scale-actions``) the output is instead ``Policy.rescale`` of that:
  ``action_low + (a + 1) / 2 * (action_high - action_low)``, the per-step change in m, rad and h.

Baked in: observation normalisation when the policy has it ((obs - mean) / std clipped to
+-`OBS_CLIP`), the ReLU MLP, only the mean half of the last layer (the log-std half does not
affect the deterministic action, so it is dropped), tanh, and the optional action scaling. Not
baked in: `Policy`'s input checks (shape, NaN/inf), and sampling.

``metadata_props`` carry the policy file's `PolicyMetadata` JSON (key ``"forcegrasp.policy"``, the
same as in the policy file) plus ``object_name``, ``force_feedback``, ``obs_layout``,
``action_layout`` (JSON) and ``action_units`` (``"normalized"`` or ``"scaled"``), so a deployed
model can be matched to its env without the original file.
"""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import numpy as np

from forcegrasp.policy import OBS_CLIP
from forcegrasp.policy_file import METADATA_KEY, PolicyFileError, PolicyMetadata, atomic_write, load_policy_file

INPUT_NAME = "observation"
OUTPUT_NAME = "action"
# Opset 17 / IR 8: old enough for every onnxruntime the project accepts (>= 1.18); onnx.helper
# would otherwise stamp its newest IR version, which older runtimes refuse to load.
OPSET = 17
IR_VERSION = 8


def policy_to_onnx(weights: dict[str, np.ndarray], meta: PolicyMetadata, scale_actions: bool = False):
    """The checked ``onnx.ModelProto`` of a policy (weights and metadata as `load_policy_file` gives)."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    meta.validate()  # the action range included: scale_actions needs it
    inits, nodes = [], []

    def const(name: str, value) -> str:
        inits.append(numpy_helper.from_array(np.asarray(value, dtype=np.float32), name))
        return name

    x = INPUT_NAME
    if meta.obs_norm:
        # Multiply by 1/std as Policy's numpy path does (rather than divide): bit-identical inputs to the MLP.
        mean = np.asarray(weights["obs_mean"], np.float32)
        inv_std = (1.0 / np.asarray(weights["obs_std"], np.float32)).astype(np.float32)
        nodes += [
            helper.make_node("Sub", [x, const("obs_mean", mean)], ["obs_centered"]),
            helper.make_node("Mul", ["obs_centered", const("obs_inv_std", inv_std)], ["obs_scaled"]),
            helper.make_node("Clip", ["obs_scaled", const("obs_clip_min", -OBS_CLIP), const("obs_clip_max", OBS_CLIP)],
                             ["obs_normalized"]),
        ]
        x = "obs_normalized"

    n_layers = len(meta.hidden) + 1
    for i in range(n_layers):
        w = np.asarray(weights[f"layers.{i}.weight"], np.float32).T  # (in, out): x @ w
        b = np.asarray(weights[f"layers.{i}.bias"], np.float32)
        last = i == n_layers - 1
        if last:  # keep the mean half only; the log-std half never reaches the deterministic action
            w, b = w[:, : meta.act_dim], b[: meta.act_dim]
        nodes += [
            helper.make_node("MatMul", [x, const(f"layers.{i}.weight_t", np.ascontiguousarray(w))], [f"layers.{i}.matmul"]),
            helper.make_node("Add", [f"layers.{i}.matmul", const(f"layers.{i}.bias", b)], [f"layers.{i}.out"]),
        ]
        x = f"layers.{i}.out"
        if not last:
            nodes.append(helper.make_node("Relu", [x], [f"layers.{i}.relu"]))
            x = f"layers.{i}.relu"

    if scale_actions:
        low, high = np.asarray(meta.action_low, np.float32), np.asarray(meta.action_high, np.float32)
        # Policy.rescale: low + (a + 1) * 0.5 * (high - low), in the same order of float32 operations.
        nodes += [
            helper.make_node("Tanh", [x], ["action_normalized"]),
            helper.make_node("Add", ["action_normalized", const("one", 1.0)], ["action_shifted"]),
            helper.make_node("Mul", ["action_shifted", const("half", 0.5)], ["action_halved"]),
            helper.make_node("Mul", ["action_halved", const("action_span", high - low)], ["action_span_scaled"]),
            helper.make_node("Add", [const("action_low", low), "action_span_scaled"], [OUTPUT_NAME]),
        ]
    else:
        nodes.append(helper.make_node("Tanh", [x], [OUTPUT_NAME]))

    graph = helper.make_graph(
        nodes,
        f"forcegrasp_{meta.object_name or 'policy'}",
        [helper.make_tensor_value_info(INPUT_NAME, TensorProto.FLOAT, ["batch", meta.obs_dim])],
        [helper.make_tensor_value_info(OUTPUT_NAME, TensorProto.FLOAT, ["batch", meta.act_dim])],
        initializer=inits,
    )
    model = helper.make_model(graph, producer_name="forcegrasp", opset_imports=[helper.make_opsetid("", OPSET)],
                              doc_string=f"ForceGrasp deterministic policy: {INPUT_NAME} -> {OUTPUT_NAME} "
                                         f"({'scaled' if scale_actions else 'normalized, [-1, 1]'})")
    model.ir_version = IR_VERSION
    helper.set_model_props(model, {
        METADATA_KEY: meta.to_json(),
        "object_name": meta.object_name,
        "force_feedback": json.dumps(bool(meta.force_feedback)),
        "obs_layout": json.dumps(meta.obs_layout),
        "action_layout": json.dumps(meta.action_layout),
        "action_units": "scaled" if scale_actions else "normalized",
    })
    onnx.checker.check_model(model, full_check=True)
    return model


def export_policy(src: str | os.PathLike, dst: str | os.PathLike, scale_actions: bool = False) -> Path:
    """Write policy file ``src`` as ONNX to ``dst`` atomically; raises `PolicyFileError`,
    `FileNotFoundError` (no ``src``) or `NotADirectoryError` (no folder for ``dst``) and then writes nothing."""
    dst = Path(dst)
    weights, meta = load_policy_file(src)
    model = policy_to_onnx(weights, meta, scale_actions=scale_actions)
    if not dst.parent.is_dir():  # checked here: atomic_write would create missing folders
        raise NotADirectoryError(errno.ENOENT, "output folder does not exist", str(dst.parent))
    if dst.is_dir():
        raise IsADirectoryError(errno.EISDIR, "is a folder; give the path of the .onnx file to write", str(dst))
    with atomic_write(dst) as f:
        f.write(model.SerializeToString())
    return dst


def onnx_metadata(model_or_path) -> PolicyMetadata:
    """The `PolicyMetadata` an exported model carries (a path or an ``onnx.ModelProto``)."""
    import onnx

    model = model_or_path if isinstance(model_or_path, onnx.ModelProto) else onnx.load(os.fspath(model_or_path))
    props = {p.key: p.value for p in model.metadata_props}
    if METADATA_KEY not in props:
        raise PolicyFileError(f"not a ForceGrasp ONNX export (no {METADATA_KEY!r} metadata)")
    return PolicyMetadata.from_json(props[METADATA_KEY])
