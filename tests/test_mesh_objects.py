"""Mesh objects (issue 49, "bring your own object"): `forcegrasp object import` refuses bad input with
its message and leaves nothing behind; mass and inertia come from the mesh at uniform density; the
convex parts are convex and cover the mesh; a mesh object builds, resets and steps; the functional
part (a region of the mesh) is what the label's functional-contact check measures.

Small meshes made here (a cube, an L-shaped block, a cone) keep CoACD fast; the mesh twin of the
primitive mug (its primitives written as a mesh and as ready-made convex parts: no decomposition)
reuses the primitive mug's label."""

import json
import os
import subprocess
import sys

import mujoco
import numpy as np
import pytest
import trimesh

from forcegrasp import objects as objects_module
from forcegrasp.label_checks import hold_check
from forcegrasp.labels import load_label
from forcegrasp.mesh_import import MeshImportError, coverage, import_mesh
from forcegrasp.meshes import clip_convex, convex_triangles, mesh_volume, read_obj, region_halfspaces, write_obj
from forcegrasp.objects import ObjectFileError, load_object, load_object_file, parse_object
from forcegrasp.scene import SceneIndex, build_model, part_geoms


# ------------------------------------------------------------------------------------ helpers
def l_block(side=0.02, depth=0.03) -> trimesh.Trimesh:
    """An L-shaped prism (6 x 6 x 3 cm): the smallest non-convex solid, one watertight shell."""
    poly = np.array([(0, 0), (3, 0), (3, 1), (1, 1), (1, 3), (0, 3)], float) * side
    n = len(poly)
    V = np.vstack([np.c_[poly, np.zeros(n)], np.c_[poly, np.full(n, depth)]])
    fan = [(3, i, (i + 1) % n) for i in (4, 5, 0, 1)]  # from the reflex corner, which sees every vertex
    F = [(a, c, b) for a, b, c in fan] + [(a + n, b + n, c + n) for a, b, c in fan]
    for i in range(n):
        j = (i + 1) % n
        F += [(i, j, j + n), (i, j + n, i + n)]
    mesh = trimesh.Trimesh(V, np.array(F))
    trimesh.repair.fix_normals(mesh)
    return mesh


def files_under(path) -> set:
    return {str(p.relative_to(path)) for p in path.rglob("*")}


@pytest.fixture
def assets(tmp_path):
    root = tmp_path / "assets"
    (root / "objects").mkdir(parents=True)
    (root / "meshes").mkdir()
    return root


FAST_COACD = {"preprocess_mode": "off", "mcts_iterations": 50, "resolution": 1000}


def run_import(assets, file, **kw):
    args = {"name": "thing", "mass": 0.2, "part": "box:0.05,0.01,0.015,0.01,0.01,0.01", "center": "source",
            "assets_dir": assets, "picture": False, "log": lambda *_: None, "coacd_options": FAST_COACD}
    args.update(kw)
    return import_mesh(file, **args)


# ------------------------------------------------------------------------------------ refusals
def _write(tmp_path, name, mesh=None, text=None):
    path = tmp_path / name
    if text is not None:
        path.write_text(text)
    else:
        mesh.export(str(path))
    return path


def _bad_inputs(tmp_path):
    box = trimesh.creation.box(extents=[0.05, 0.05, 0.05])
    box.apply_translation([0, 0, 0.025])
    big = trimesh.creation.box(extents=[8.2, 12.2, 10.0])  # a mug in mm read as m
    small = trimesh.creation.box(extents=[0.00082, 0.00122, 0.001])  # a mug in m read as km
    flat = trimesh.Trimesh([[0, 0, 0], [0.05, 0, 0], [0.05, 0.05, 0], [0, 0.05, 0], [0.025, 0.025, 0]],
                           [[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]], process=False)
    # a box with a fin: one edge shared by three triangles, which no hole filling can close
    fin = trimesh.Trimesh(np.vstack([box.vertices, [[0.1, 0.0, 0.025]]]),
                          np.vstack([box.faces, [[*box.faces[0][:2], len(box.vertices)]]]), process=False)
    return {
        "not a mesh file": (_write(tmp_path, "notes.txt", text="v 0 0 0\n"), {}, r"not a mesh file"),
        "text named .obj": (_write(tmp_path, "letter.obj", text="Dear reader,\nthis is no mesh.\n"), {},
                            r"empty mesh: no triangles"),
        "no triangles": (_write(tmp_path, "points.obj", text="v 0 0 0\nv 1 0 0\nv 0 1 0\n"), {},
                         r"empty mesh: no triangles"),
        "flat": (_write(tmp_path, "flat.obj", flat), {}, r"degenerate mesh"),
        "100x too big": (_write(tmp_path, "big.stl", big), {}, r"too big for a hand.*try --scale 0\.01"),
        "100x too small": (_write(tmp_path, "small.stl", small), {}, r"too small for a hand.*try --scale 100"),
        "open, unrepairable": (_write(tmp_path, "fin.obj", fin), {"part": "box:0,0,0.05,0.01,0.01,0.01"},
                               r"not watertight.*mass and inertia need a closed surface"),
        "part off the mesh": (_write(tmp_path, "box.stl", box), {"part": "box:0.3,0,0.02,0.01,0.01,0.01"},
                              r"--part box:0.3,0,0.02,0.01,0.01,0.01: the region touches no surface"),
        "part inside the solid": (_write(tmp_path, "box2.stl", box), {"part": "sphere:0,0,0.025,0.01"},
                                  r"the region touches no surface"),
        "unknown group": (_write(tmp_path, "box3.obj", box), {"part": "group:handle"},
                          r"no group or object 'handle'"),
        "bad part syntax": (_write(tmp_path, "box4.stl", box), {"part": "cube:1,2,3"}, r"expected box:"),
        "bad mass": (_write(tmp_path, "box5.stl", box), {"mass": -1.0}, r"--mass"),
    }


def test_each_bad_input_gets_its_message_and_leaves_nothing_behind(tmp_path, assets):
    cases = _bad_inputs(tmp_path)
    before = files_under(assets)
    for what, (path, kw, message) in cases.items():
        with pytest.raises(MeshImportError, match=message):
            run_import(assets, path, **kw)
        assert files_under(assets) == before, what  # no object, no mesh folder, no temporary folder


def test_a_pose_that_tips_over_is_refused_after_the_decomposition_and_nothing_stays(tmp_path, assets):
    cone = trimesh.creation.cone(radius=0.03, height=0.08, sections=24)  # standing on its tip once turned over
    path = _write(tmp_path, "cone.stl", cone)
    with pytest.raises(MeshImportError, match="does not rest in this pose"):
        run_import(assets, path, euler_deg=(172, 0, 0), part="sphere:0,0,0.07,0.03")
    assert files_under(assets) == {"objects", "meshes"}


def test_the_command_refuses_with_a_message_and_writes_nothing(tmp_path, assets):
    big = _write(tmp_path, "big.stl", trimesh.creation.box(extents=[82.0, 122.0, 100.0]))
    env = {**os.environ, "FORCEGRASP_ASSETS": str(assets)}
    out = subprocess.run([sys.executable, "-m", "forcegrasp.cli", "object", "import", str(big), "--name", "mug2",
                          "--mass", "0.35", "--part", "sphere:0,0,0.05,0.01", "--no-picture"],
                         env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2, out.stdout + out.stderr
    assert "too big for a hand" in out.stderr and "nothing was written" in out.stderr
    assert files_under(assets) == {"objects", "meshes"}


# ------------------------------------------------------------------------------------ a good import
@pytest.fixture
def l_object(tmp_path, assets, monkeypatch):
    """The L block with one triangle missing (the import repairs it), imported into ``assets``."""
    mesh = l_block()
    mesh.update_faces(np.arange(1, len(mesh.faces)))
    assert not mesh.is_watertight
    path = _write(tmp_path, "lblock.obj", mesh)
    result = run_import(assets, path, name="lblock")
    monkeypatch.setattr(objects_module, "ASSETS_DIR", assets)
    return result, load_object("lblock")


def test_an_import_repairs_measures_and_writes_the_object(l_object, assets):
    result, obj = l_object
    assert not result.watertight_source and any("filled holes" in r for r in result.repairs)
    assert result.volume_m3 == pytest.approx((36 - 16) * 3e-6, rel=1e-6)  # (6 x 6 - 4 x 4 cm) x 3 cm
    assert files_under(assets) == {"objects", "objects/lblock.json", "meshes", "meshes/lblock",
                                   "meshes/lblock/lblock.obj", "meshes/lblock/visual.obj", "meshes/lblock/parts.obj"}
    assert obj.mesh is not None and obj.functional_part == ("functional",) and obj.regions["functional"].kind == "box"
    assert obj.mesh.measured["convex_parts"] == result.parts >= 2
    text = result.summary()
    for word in ("6.0 x 6.0 x 3.0 cm", "watertight: no, repaired", "mass 0.200 kg", "inertia", "convex parts:"):
        assert word in text
    with pytest.raises(MeshImportError, match="exists"):  # a second import does not overwrite it
        run_import(assets, obj.mesh.visual, name="lblock")


def test_decomposed_parts_are_convex_and_cover_the_mesh(l_object):
    """Each part is its own convex hull (volume equal within 1e-9 relative); the parts' union covers
    >= 97 % of the mesh's volume and is at most 110 % of it (Monte Carlo, 20,000 points)."""
    _, obj = l_object
    (_, V, F), = read_obj(obj.mesh.visual)
    parts = read_obj(obj.mesh.parts)
    assert len(parts) >= 2  # an L is not convex
    for _, PV, PF in parts:
        volume = mesh_volume(PV, PF)
        assert volume > 0 and trimesh.Trimesh(PV, PF).is_watertight
        assert volume == pytest.approx(trimesh.convex.convex_hull(PV).volume, rel=1e-9)
    cover = coverage(V, F, [PV for _, PV, _ in parts])
    assert cover["covered"] >= 0.97 and cover["union_over_mesh"] <= 1.10, cover


def test_unit_cube_mass_and_inertia_match_the_analytic_values(tmp_path, assets, monkeypatch):
    """A cube of side 1 in the file, --scale 0.05: a 5 cm cube of 0.3 kg, I = m a^2 / 6 about each axis,
    from trimesh at import and from MuJoCo in the scene (at mass scale 1 and 2)."""
    cube = trimesh.creation.box(extents=[1.0, 1.0, 1.0])
    path = _write(tmp_path, "cube.stl", cube)
    result = run_import(assets, path, name="cube", mass=0.3, scale=0.05, part="box:0,0,0.05,0.01,0.01,0.01",
                        center="com")
    a, m = 0.05, 0.3
    expected = m * a * a / 6.0
    assert result.volume_m3 == pytest.approx(a ** 3, rel=1e-9)
    np.testing.assert_allclose(result.inertia, np.eye(3) * expected, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(result.center_of_mass, [0, 0, a / 2], atol=1e-12)
    assert result.parts == 1
    monkeypatch.setattr(objects_module, "ASSETS_DIR", assets)
    obj = load_object("cube")
    for scale in (1.0, 2.0):
        model = build_model(obj, mass_scale=scale)
        body = model.body("object").id
        assert model.body_mass[body] == pytest.approx(m * scale, rel=1e-9)
        np.testing.assert_allclose(model.body_inertia[body], [expected * scale] * 3, rtol=1e-6)
        np.testing.assert_allclose(model.body_ipos[body], [0, 0, a / 2], atol=1e-7)


def test_a_group_of_the_obj_file_becomes_a_box_region(tmp_path, assets, monkeypatch):
    """``--part group:NAME``: the named group's bounding box, grown by 1 mm, in the object frame
    (after --scale and the shift onto the table)."""
    base = trimesh.creation.box(extents=[40, 40, 20])
    base.apply_translation([0, 0, 10])
    knob = trimesh.creation.box(extents=[10, 10, 10])
    knob.apply_translation([0, 0, 25])
    lines = []
    for group, solid, offset in (("base", base, 0), ("knob", knob, len(base.vertices))):
        lines += [f"v {x} {y} {z}" for x, y, z in solid.vertices]
    for group, solid, offset in (("base", base, 0), ("knob", knob, len(base.vertices))):
        lines.append(f"g {group}")
        lines += [f"f {a + 1 + offset} {b + 1 + offset} {c + 1 + offset}" for a, b, c in solid.faces]
    path = tmp_path / "stack.obj"
    path.write_text("\n".join(lines) + "\n")
    run_import(assets, path, name="stack", scale=0.001, part="group:knob", part_name="knob")
    monkeypatch.setattr(objects_module, "ASSETS_DIR", assets)
    obj = load_object("stack")
    knob_region = obj.regions["knob"]
    assert knob_region.kind == "box" and knob_region.group == "knob"
    np.testing.assert_allclose(knob_region.center, [0, 0, 0.025], atol=1e-9)
    np.testing.assert_allclose(knob_region.size, [0.006, 0.006, 0.006], atol=1e-9)
    m = build_model(obj)
    assert part_geoms(m, obj, "knob")


# ------------------------------------------------------------------------------------ regions
def test_a_region_clips_the_convex_parts_and_a_sphere_is_a_tangent_polytope():
    cube = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    piece = clip_convex(cube, *region_halfspaces("box", [1, 1, 1], [0.5, 0.5, 0.5]))
    np.testing.assert_allclose(piece.min(axis=0), [0.5] * 3) and np.testing.assert_allclose(piece.max(axis=0), [1] * 3)
    V, F = convex_triangles(piece)
    assert mesh_volume(V, F) == pytest.approx(0.125)
    assert clip_convex(cube, *region_halfspaces("box", [3, 3, 3], [0.5, 0.5, 0.5])) is None
    ball = clip_convex(cube * 4 - 2, *region_halfspaces("sphere", [0, 0, 0], [1.0]))
    r = np.linalg.norm(ball, axis=1)
    assert 1.0 <= r.min() and r.max() <= 1.0715  # corners of the tangent polytope


MUG_FILE = load_object("mug").path  # the shipped primitive mug (tests below point the assets elsewhere)


def mug_twin(assets, region=None) -> None:
    """The primitive mug written as a mesh object: its visual mesh the union of its primitives (a
    48-sided cylinder and three boxes, overlapping shells), its convex parts those same four solids."""
    mug = load_object_file(MUG_FILE)
    blocks = []
    for g in mug.geoms:
        if g.type == "cylinder":
            solid = trimesh.creation.cylinder(radius=g.size[0], height=2 * g.size[1], sections=48)
        else:
            solid = trimesh.creation.box(extents=2 * np.asarray(g.size))
        solid.apply_translation(g.pos)
        blocks.append((g.name, np.asarray(solid.vertices), np.asarray(solid.faces)))
    folder = assets / "meshes" / "mug_twin"
    folder.mkdir(parents=True, exist_ok=True)
    visual = trimesh.util.concatenate([trimesh.Trimesh(V, F) for _, V, F in blocks])
    write_obj(folder / "visual.obj", [("mug_twin", visual.vertices, visual.faces)])
    write_obj(folder / "parts.obj", blocks)
    raw = json.loads(mug.path.read_text())
    for key in ("geoms",):
        raw.pop(key)
    raw.update(name="mug_twin", mesh={"visual": "meshes/mug_twin/visual.obj", "parts": "meshes/mug_twin/parts.obj"},
               regions={"handle": region or {"box": [0.064, 0.0, 0.055, 0.023, 0.007, 0.039]},
                        "handle_top": {"box": [0.0625, 0.0, 0.088, 0.0225, 0.007, 0.006]}},
               functional_part=["handle"])
    raw["grasp_hint"]["contacts"] = {"th": ["handle_top"], "mf": ["handle"]}
    (assets / "objects" / "mug_twin.json").write_text(json.dumps(raw))


def test_the_mesh_twin_of_the_mug_builds_resets_and_steps(assets, monkeypatch):
    from forcegrasp.env import FunctionalGraspEnv

    mug_twin(assets)
    monkeypatch.setattr(objects_module, "ASSETS_DIR", assets)
    obj = load_object("mug_twin")
    env = FunctionalGraspEnv("mug_twin", label=load_label("mug"), mass_scale_range=(1.0, 5.0))
    m, ix = env.model, env.ix
    assert len(ix.object_geoms) == 4  # the convex parts collide; the visual mesh and region pieces do not
    assert all(m.geom_contype[g] == 0 for p in ("handle", "handle_top") for g in part_geoms(m, obj, p))
    assert m.geom_contype[m.geom("mug_twin/mesh").id] == 0
    obs, info = env.reset(seed=0)
    mass0 = m.body_mass[ix.object_body]
    for _ in range(20):
        obs, reward, term, trunc, info = env.step(env.action_space.sample())
        assert np.all(np.isfinite(obs)) and np.isfinite(reward)
        if term or trunc:
            break
    env.reset(seed=1)
    assert m.body_mass[ix.object_body] != mass0  # per-episode mass randomisation scales the mesh's mass too
    scale = m.body_mass[ix.object_body] / env._unit_mass
    np.testing.assert_allclose(m.body_inertia[ix.object_body], scale * env._unit_inertia, rtol=1e-9)


def test_a_functional_region_the_goal_grasp_does_not_touch_fails_the_check(assets, monkeypatch):
    """The primitive mug's goal grasp on its mesh twin: the index finger touches the handle region;
    move the region to the far side of the mug and the same grasp fails the functional-contact check."""
    monkeypatch.setattr(objects_module, "ASSETS_DIR", assets)
    goal = load_label("mug").goal.q
    mug_twin(assets)
    touched = hold_check(load_object("mug_twin"), goal, mass_scale=1.0, seconds=0.3)
    assert touched["functional_contact"], touched
    mug_twin(assets, region={"box": [-0.04, 0.0, 0.05, 0.006, 0.03, 0.03]})  # the wall opposite the handle
    moved = hold_check(load_object("mug_twin"), goal, mass_scale=1.0, seconds=0.3)
    assert not moved["functional_contact"] and moved["functional_gap_m"] > 0.02, moved


# ------------------------------------------------------------------------------------ object files
def test_malformed_mesh_entries_name_the_field(assets, monkeypatch):
    mug_twin(assets)
    path = assets / "objects" / "mug_twin.json"
    good = json.loads(path.read_text())
    cases = {
        "mesh.visual": {"mesh": {**good["mesh"], "visual": "meshes/mug_twin/nothing.obj"}},
        "inside the assets folder": {"mesh": {**good["mesh"], "parts": "../../etc/parts.obj"}},
        "mesh.scale": {"mesh": {**good["mesh"], "scale": 0}},
        "regions.handle.box": {"regions": {"handle": {"box": [0, 0, 0, 1, 1]}}},
        "regions.handle": {"regions": {"handle": {"cone": [0, 0, 0, 1]}}},
        "functional_part": {"functional_part": ["spout"]},
        "needs a 'mesh'": {"mesh": None},
    }
    for what, change in cases.items():
        raw = {**good, **change}
        if raw.get("mesh") is None:
            raw.pop("mesh")
            raw["geoms"] = [{"name": "a", "type": "box", "size": [0.01, 0.01, 0.01]}]
        path.write_text(json.dumps(raw))
        with pytest.raises(ObjectFileError, match=what.replace(".", r"\.")):
            load_object_file(path)
    with pytest.raises(ObjectFileError, match="missing field 'geoms'"):
        parse_object({k: v for k, v in good.items() if k not in ("mesh", "regions")}, path=path)


def test_a_changed_source_is_refused(assets, tmp_path, monkeypatch):
    cube = _write(tmp_path, "cube.obj", trimesh.creation.box(extents=[0.05, 0.05, 0.05]))
    run_import(assets, cube, name="cube", part="sphere:0,0,0.05,0.01")
    monkeypatch.setattr(objects_module, "ASSETS_DIR", assets)
    load_object("cube")
    source = assets / "meshes" / "cube" / "cube.obj"
    source.write_text(source.read_text() + "\n# edited\n")
    with pytest.raises(ObjectFileError, match="changed since it was imported"):
        load_object("cube")


# ------------------------------------------------------------------------------------ the shipped mug
def test_the_shipped_mesh_mug_has_its_files_notice_and_mass_properties():
    obj = load_object("mug_mesh")
    folder = obj.mesh.visual.parent
    assert (folder / "NOTICE").is_file() and "zlib" in (folder / "NOTICE").read_text().lower()
    assert (folder / "mug.obj").is_file()
    m = build_model(obj)
    body = m.body("object").id
    assert m.body_mass[body] == pytest.approx(0.35)
    measured = np.asarray(obj.mesh.measured["inertia_at_com"])
    np.testing.assert_allclose(sorted(m.body_inertia[body]), np.linalg.eigvalsh(measured), rtol=1e-3)
    ix = SceneIndex.of(m)
    assert len(ix.object_geoms) == obj.mesh.measured["convex_parts"]
    assert part_geoms(m, obj, "handle") and part_geoms(m, obj, "handle_top")
    (_, V, F), = read_obj(obj.mesh.visual)
    parts = [PV for _, PV, _ in read_obj(obj.mesh.parts)]
    cover = coverage(V, F, parts, samples=4000)
    assert cover["covered"] >= 0.95 and cover["union_over_mesh"] <= 1.3, cover


def test_the_scene_of_a_mesh_object_carries_its_visual_mesh_and_functional_part_as_triangles():
    """Foxglove draws a mesh object from the episode log's /scene: its visual mesh and the functional
    part's pieces as triangle lists (valid foxglove.SceneUpdate), never the collision parts."""
    import jsonschema

    from forcegrasp.env import FunctionalGraspEnv
    from forcegrasp.mcap_log.messages import scene_json
    from forcegrasp.mcap_log.schemas import SCHEMAS

    env = FunctionalGraspEnv("mug_mesh")
    m = env.model
    scene = json.loads(scene_json(m, env.ix, "mug_mesh"))
    jsonschema.Draft7Validator(SCHEMAS["foxglove.SceneUpdate"]).validate(scene)
    (entity,) = [e for e in scene["entities"] if e["id"] == "object"]
    visual = m.geom_dataid[m.geom("mug_mesh/mesh").id]
    regions = part_geoms(m, load_object("mug_mesh"), "handle") + part_geoms(m, load_object("mug_mesh"), "handle_top")
    assert len(entity["triangles"]) == 1 + len(regions)  # the collision parts stay out
    mesh = entity["triangles"][0]
    assert len(mesh["points"]) == m.mesh_vertnum[visual] and len(mesh["indices"]) == 3 * m.mesh_facenum[visual]
    assert max(mesh["indices"]) < len(mesh["points"]) and mesh["color"]["a"] == 1.0
