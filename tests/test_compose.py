"""Static checks of the container files (Dockerfile, .dockerignore, compose.yaml).

No Docker engine runs here, so everything is checked by reading the files: the compose file's
FORCEGRASP_* variables go through the real configuration loader, every service's command line
(entrypoint + command, after compose's ${...}/$$ interpolation) is parsed by the real
``forcegrasp`` CLI, and the Dockerfile's install and entry point are read.
"""

from __future__ import annotations

import fnmatch
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from forcegrasp.cli import SERVICES
from forcegrasp.config import CONFIG_FILE_ENV, ENV_PREFIX, SECTIONS, load_config

REPO = Path(__file__).resolve().parent.parent
COMPOSE = REPO / "compose.yaml"
SERVICE_NAMES = ("learner", "actor", "evaluator")
LEARNER_PORT = 7447


# --------------------------------------------------------------------------------------------
# Reading the files the way compose and docker do
# --------------------------------------------------------------------------------------------

_VAR = re.compile(r"\$\$|\$\{([A-Za-z_][A-Za-z0-9_]*)(?:(:?-)([^}]*))?\}|\$([A-Za-z_][A-Za-z0-9_]*)")


def interpolate(text: str) -> str:
    """Compose's interpolation with an empty shell: ``$$`` -> ``$``, ``${VAR:-default}`` -> default.

    A variable without a default would silently become empty under compose: refused here.
    """
    def sub(m: re.Match) -> str:
        if m.group(0) == "$$":
            return "$"
        if m.group(2) is None:
            raise AssertionError(f"compose.yaml: {m.group(0)} has no default (write ${{NAME:-value}})")
        return m.group(3)

    return _VAR.sub(sub, text)


def load_compose() -> dict:
    with open(COMPOSE) as f:
        return yaml.safe_load(f)


def services() -> dict:
    return load_compose()["services"]


def environment(service: dict) -> dict[str, str]:
    env = service.get("environment") or {}
    if isinstance(env, list):  # the "KEY=value" list form
        env = dict(item.split("=", 1) for item in env)
    return {k: interpolate(str(v)) for k, v in env.items()}


def argv_list(value) -> list[str]:
    """compose/Dockerfile command or entrypoint, as a list (a string is split like a shell)."""
    if value is None:
        return []
    items = shlex.split(value) if isinstance(value, str) else list(value)
    return [interpolate(str(v)) for v in items]


def dockerfile_instructions() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) pairs with continuation lines joined and comments dropped."""
    out, pending = [], ""
    for line in (REPO / "Dockerfile").read_text().splitlines():
        stripped = line.strip()
        if not pending and (not stripped or stripped.startswith("#")):
            continue
        if stripped.startswith("#"):  # a comment inside a continued instruction
            continue
        if stripped.endswith("\\"):
            pending += stripped[:-1] + " "
            continue
        text = pending + stripped
        pending = ""
        if text:
            word, _, rest = text.partition(" ")
            out.append((word.upper(), rest.strip()))
    assert not pending, "Dockerfile ends inside a continued line"
    return out


def instructions(name: str) -> list[str]:
    return [args for word, args in dockerfile_instructions() if word == name]


def image_entrypoint() -> list[str]:
    (entry,) = instructions("ENTRYPOINT")[-1:]
    return json.loads(entry)


def dockerignore_patterns() -> list[str]:
    lines = (REPO / ".dockerignore").read_text().splitlines()
    return [line.strip().rstrip("/") for line in lines if line.strip() and not line.startswith("#")]


def dockerignored(rel: str) -> bool:
    """True if ``rel`` (or a folder above it) matches a .dockerignore pattern (no '!' rules used)."""
    parts = rel.split("/")
    candidates = ["/".join(parts[: i + 1]) for i in range(len(parts))]
    for pattern in dockerignore_patterns():
        assert not pattern.startswith("!"), "exceptions in .dockerignore: extend dockerignored()"
        for cand in candidates:
            if fnmatch.fnmatch(cand, pattern) or (pattern.startswith("**/") and (
                    fnmatch.fnmatch(cand, pattern[3:]) or fnmatch.fnmatch(cand, pattern))):
                return True
    return False


def config_of(name: str):
    env = {k: v for k, v in environment(services()[name]).items() if k.startswith(ENV_PREFIX)}
    return load_config(env=env)


# --------------------------------------------------------------------------------------------
# compose.yaml
# --------------------------------------------------------------------------------------------

def test_services_exist_and_build_from_the_repo_dockerfile():
    svcs = services()
    assert set(SERVICE_NAMES) <= set(svcs), f"compose.yaml services: {sorted(svcs)}"
    for name in SERVICE_NAMES:
        build = svcs[name].get("build")
        assert build is not None, f"{name}: no build section"
        if isinstance(build, str):
            build = {"context": build}
        context = (COMPOSE.parent / build.get("context", ".")).resolve()
        assert context == REPO, f"{name}: build context {context} is not the repository"
        assert (context / build.get("dockerfile", "Dockerfile")).is_file(), f"{name}: no Dockerfile"
    images = {interpolate(str(svcs[name].get("image", ""))) for name in SERVICE_NAMES}
    assert images == {"forcegrasp:latest"}, (
        f"one image for every service (compose builds it once under that tag), not {images}")


def test_every_forcegrasp_variable_is_a_real_setting():
    for name, svc in services().items():
        env = environment(svc)
        assert CONFIG_FILE_ENV not in env
        for var in env:
            if var.startswith(ENV_PREFIX):
                # load_config ignores unknown sections (FORCEGRASP_ASSETS is not a setting), so a
                # misspelt section would vanish silently: it must be one of ours.
                section = var[len(ENV_PREFIX):].lower().partition("_")[0]
                assert section in SECTIONS, f"{name}: {var} names no configuration section"
        config_of(name)  # raises ConfigError on an unknown key or a bad value


def test_settings_have_the_intended_values():
    learner, actor, evaluator = (config_of(n) for n in SERVICE_NAMES)
    assert learner.network.endpoints_for("learner") == ([f"tcp/0.0.0.0:{LEARNER_PORT}"], [])
    assert learner.run.output_dir == "/data"
    for config in (actor, evaluator):
        listen, connect = config.network.endpoints_for("actor")
        assert connect == [f"tcp/learner:{LEARNER_PORT}"], "must reach the learner by its service name"
        assert listen == ["tcp/0.0.0.0:0"], "peers must be reachable from the other containers"
    assert evaluator.evaluator.http_host == "0.0.0.0"
    assert evaluator.run.output_dir == learner.run.output_dir
    for key in ("run.name", "env.object", "env.force_feedback"):  # the services must agree
        section, field = key.split(".")
        values = {getattr(getattr(c, section), field) for c in (learner, actor, evaluator)}
        assert len(values) == 1, f"{key} differs between services: {values}"


def published(service: dict) -> dict[int, int]:
    """{container port: host port} from the short "HOST:CONTAINER" syntax."""
    out = {}
    for item in service.get("ports", []):
        host, _, container = interpolate(str(item)).rpartition(":")
        out[int(container.split("/")[0])] = int(host.rpartition(":")[2])
    return out


def test_ports_and_volumes():
    compose = load_compose()
    svcs = compose["services"]
    assert published(svcs["learner"]).get(LEARNER_PORT) == LEARNER_PORT, "remote actors need the learner port"
    port = config_of("evaluator").evaluator.http_port
    assert port != 0 and published(svcs["evaluator"]).get(port) == 8080
    for name in ("learner", "evaluator"):
        mounts = [str(v).split(":") for v in svcs[name].get("volumes", [])]
        output_dir = config_of(name).run.output_dir
        assert ["runs", output_dir] in [m[:2] for m in mounts], f"{name}: runs volume not at {output_dir}"
    assert "runs" in (compose.get("volumes") or {})


def test_actor_is_scalable():
    actor = services()["actor"]
    for key in ("container_name", "ports", "hostname"):
        assert key not in actor, f"actor: {key} stops 'docker compose up --scale actor=N'"


def container_argv(service: dict) -> list[str]:
    """What the container runs: the service's entrypoint (else the image's) + its command."""
    entry = argv_list(service["entrypoint"]) if "entrypoint" in service else image_entrypoint()
    return entry + argv_list(service.get("command"))


def run_in_shim(argv: list[str], tmp_path: Path, hostname: str) -> tuple[subprocess.CompletedProcess, list[str]]:
    """Run a container command line here, with ``forcegrasp`` a shim that records its arguments
    and runs the real CLI up to its argument parsing: a sub-command or option that does not exist,
    or a value of the wrong type, exits 2; arguments that parse exit 0 before the service starts."""
    bindir = tmp_path / "bin"
    bindir.mkdir(parents=True, exist_ok=True)
    record = tmp_path / "argv.json"
    shim = bindir / "forcegrasp"
    shim.write_text(
        f"#!{sys.executable}\n"
        "import json, sys\n"
        f"json.dump(sys.argv[1:], open({str(record)!r}, 'w'))\n"
        "import argparse\n"
        "parse = argparse.ArgumentParser.parse_args\n"
        "def parse_then_stop(self, *a, **k):\n"
        "    parse(self, *a, **k)\n"
        "    raise SystemExit(0)\n"
        "argparse.ArgumentParser.parse_args = parse_then_stop\n"
        "from forcegrasp.cli import main\n"
        "sys.exit(main(sys.argv[1:]))\n")
    shim.chmod(0o755)
    env = dict(os.environ, PATH=f"{bindir}{os.pathsep}{os.environ['PATH']}", HOSTNAME=hostname)
    proc = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=120)
    return proc, (json.loads(record.read_text()) if record.exists() else [])


@pytest.mark.parametrize("name", ["learner", "actor"])
def test_service_commands_run_the_real_cli(name, tmp_path):
    argv = container_argv(services()[name])
    proc, args = run_in_shim(argv, tmp_path, hostname="c0ffee123456")
    assert proc.returncode == 0, f"{name}: {argv} failed:\n{proc.stdout}\n{proc.stderr}"
    assert args and args[0] == name, f"{name}: the container runs forcegrasp {args}"


def test_actor_replicas_get_distinct_ids_and_seeds(tmp_path):
    """The actor's defaults (actor-<pid>, run.seed + 1000) are equal in every container."""
    argv = container_argv(services()["actor"])
    seen = []
    for host in ("aaaaaaaaaaaa", "bbbbbbbbbbbb"):
        proc, args = run_in_shim(argv, tmp_path / host, hostname=host)
        assert proc.returncode == 0, proc.stderr
        opts = dict(zip(args[1::2], args[2::2]))
        assert opts.get("--id") == f"actor-{host}", args
        seen.append(int(opts["--seed"]))
    assert seen[0] != seen[1]


def test_evaluator_is_declared_and_enabled_once_it_exists(tmp_path):
    evaluator = services()["evaluator"]
    assert argv_list(evaluator.get("command"))[:1] == ["evaluator"]
    if "evaluator" not in SERVICES:
        # Issue 5 builds `forcegrasp evaluator`. Until then plain `docker compose up` must not
        # start a container that can only fail, so the service sits behind a profile.
        assert evaluator.get("profiles"), "evaluator: keep it behind a profile until the sub-command exists"
        return
    assert not evaluator.get("profiles"), (
        "`forcegrasp evaluator` exists now: drop its `profiles` line in compose.yaml "
        "so `docker compose up` starts it")
    proc, args = run_in_shim(container_argv(evaluator), tmp_path, hostname="e0e0e0e0e0e0")
    assert proc.returncode == 0, proc.stderr
    assert args[:1] == ["evaluator"]


def compose_client() -> list[str] | None:
    """`docker compose` (v2 plugin), else a standalone `docker-compose`; None if neither runs."""
    docker = shutil.which("docker")
    if docker and subprocess.run([docker, "compose", "version"], capture_output=True).returncode == 0:
        return [docker, "compose"]
    legacy = shutil.which("docker-compose")
    if legacy and subprocess.run([legacy, "version"], capture_output=True).returncode == 0:
        return [legacy]
    return None


@pytest.mark.docker
def test_docker_compose_validates_the_file():
    """The compose client validates the file without an engine: with the Docker tests
    (``-m docker``, after ../shared/docker/engine.sh), where a client is installed."""
    client = compose_client()
    assert client is not None, "no docker compose client: install one (docs/docker.md)"
    proc = subprocess.run(client + ["-f", str(COMPOSE), "config", "-q"], capture_output=True,
                          text=True, cwd=REPO, env={k: v for k, v in os.environ.items()
                                                    if not k.startswith(ENV_PREFIX)})
    assert proc.returncode == 0, proc.stderr


# --------------------------------------------------------------------------------------------
# Dockerfile and .dockerignore
# --------------------------------------------------------------------------------------------

def test_dockerfile_base_entrypoint_and_install():
    (base,) = instructions("FROM")
    assert base.startswith("python:3.11-slim")
    assert image_entrypoint() == ["forcegrasp"]
    installs = [r for r in instructions("RUN") if "pip install" in r]
    assert len(installs) == 2, "the dependencies in one layer, then the repository itself"
    for run in installs:
        (pip,) = [shlex.split(step) for step in run.split("&&") if "pip install" in step]
        assert "constraints.txt" == pip[pip.index("-c") + 1], "install with -c constraints.txt (the torch pin)"
        assert shlex.split(run)[-2:] == ["scripts/check_torch.py", "$TORCH"], "every install ends by checking torch"
    deps, repo = (shlex.split(r) for r in installs)
    assert "-r" in deps and "pyproject.toml" in " ".join(deps), "the dependencies come from pyproject.toml"
    assert "--no-deps" in repo and repo[repo.index("-e") + 1] == ".", "then the repository itself"
    assert (REPO / "constraints.txt").is_file()


def test_dockerfile_torch_choice_is_explicit_and_checked():
    args = dict(a.partition("=")[::2] for a in instructions("ARG"))
    assert args.get("TORCH") == "cpu" and args.get("TORCH_INDEX", "").startswith("https://")
    (deps,) = [r for r in instructions("RUN") if "-r /tmp/requirements.txt" in r]
    assert '[ "$TORCH" = cpu ]' in deps and "--extra-index-url $TORCH_INDEX" in deps
    assert services()["learner"]["build"]["args"]["TORCH"] == "${TORCH:-cpu}"


def test_check_torch_accepts_this_build_and_refuses_the_other(tmp_path):
    """The check the image build runs: this machine has the CPU wheel (constraints.txt)."""
    script = str(REPO / "scripts" / "check_torch.py")
    ok = subprocess.run([sys.executable, script, "cpu"], capture_output=True, text=True)
    assert ok.returncode == 0 and ok.stdout.startswith("ok: torch ") and "CPU-only" in ok.stdout, ok
    for wrong in ("cuda", "rocm"):
        bad = subprocess.run([sys.executable, script, wrong], capture_output=True, text=True)
        assert bad.returncode == 1 and bad.stderr.startswith("ERROR: "), bad
    # a CUDA runtime wheel installed next to the CPU torch is caught too (what pip's fallback leaves)
    site = tmp_path / "site"
    (site / "nvidia_cublas_cu12-12.4.5.8.dist-info").mkdir(parents=True)
    (site / "nvidia_cublas_cu12-12.4.5.8.dist-info" / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: nvidia-cublas-cu12\nVersion: 12.4.5.8\n")
    env = dict(os.environ, PYTHONPATH=f"{site}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    bad = subprocess.run([sys.executable, script, "cpu"], capture_output=True, text=True, env=env)
    assert bad.returncode == 1 and "nvidia-cublas-cu12" in bad.stderr and "CPU build was asked for" in bad.stderr


def test_dockerfile_rendering_backend_has_its_library():
    env = " ".join(instructions("ENV"))
    m = re.search(r"MUJOCO_GL=(\w+)", env)
    assert m and m.group(1) in ("egl", "osmesa"), "set MUJOCO_GL for offscreen rendering"
    apt = " ".join(r for r in instructions("RUN") if "apt-get install" in r)
    assert {"egl": "libegl1", "osmesa": "libosmesa6"}[m.group(1)] in apt.split()


def test_copied_paths_exist_and_are_not_dockerignored():
    copies = [c for c in instructions("COPY") if not c.startswith("--from")]
    assert copies
    for args in copies:
        words = json.loads(args) if args.startswith("[") else shlex.split(args)
        sources = [w for w in words[:-1] if not w.startswith("--")]
        for src in sources:
            assert (REPO / src).exists(), f"COPY {src}: not in the repository"
    # what `pip install -e .` and the services need must reach the build context
    for rel in ("pyproject.toml", "constraints.txt", "README.md", "common/forcegrasp/config.py",
                "services/actor/forcegrasp_actor/actor.py", "services/learner/forcegrasp_learner/learner.py", "assets/objects"):
        assert (REPO / rel).exists() and not dockerignored(rel), f"{rel} is missing from the build context"


def test_dockerignore_keeps_runs_and_caches_out():
    for rel in ("runs/mug/checkpoint.safetensors", ".git/HEAD", "common/__pycache__/env.cpython-311.pyc",
                "forcegrasp.egg-info/PKG-INFO"):
        assert dockerignored(rel), f"{rel} would be sent to the Docker build"


# --------------------------------------------------------------------------------------------
# compose.secure.yaml (the secure profile, docs/security.md)
# --------------------------------------------------------------------------------------------

def secure_services() -> dict:
    """compose.yaml with compose.secure.yaml over it: mappings merge, lists and scalars of the
    override replace (environment merges key by key, as compose does)."""
    with open(REPO / "compose.secure.yaml") as f:
        override = yaml.safe_load(f)["services"]
    merged = {}
    for name, svc in services().items():
        out = dict(svc)
        for key, value in override.get(name, {}).items():
            if key == "environment":
                out[key] = {**(svc.get(key) or {}), **value}
            elif key == "volumes":
                out[key] = list(svc.get(key) or []) + list(value)
            else:
                out[key] = value
        merged[name] = out
    return merged


def test_secure_profile_gives_every_service_credentials_and_tls(tmp_path):
    from forcegrasp.certs import make_credentials
    from forcegrasp.security import credentials_folder, session_settings

    creds = tmp_path / "creds"
    make_credentials(creds, actors=1)
    svcs = secure_services()
    for name in SERVICE_NAMES:
        env = {k: v for k, v in environment(svcs[name]).items() if k.startswith(ENV_PREFIX)}
        assert env["FORCEGRASP_NETWORK_CREDENTIALS"] == "/creds"
        assert "./creds:/creds:ro" in svcs[name]["volumes"]
        config = load_config(env={**env, "FORCEGRASP_NETWORK_CREDENTIALS": str(creds)})
        listen, connect = config.network.endpoints_for(name)
        assert all(e.startswith("tls/") for e in listen + connect), (name, listen, connect)
        if name != "learner":
            assert connect == [f"tls/learner:{LEARNER_PORT}"]  # "learner" is in the learner's certificate
    proc, args = run_in_shim(container_argv(svcs["actor"]), tmp_path / "shim", hostname="c0ffee123456")
    assert proc.returncode == 0, proc.stderr
    actor_id = dict(zip(args[1::2], args[2::2]))["--id"]
    assert actor_id == "actor-0.c0ffee123456"
    settings = session_settings(credentials_folder(creds, actor_id), "actor", "mug")
    assert settings["mode"] == "client" and settings["transport/auth/usrpwd/user"] == "actor-0"
    assert session_settings(credentials_folder(creds, "learner"), "learner", "mug")["access_control"]["enabled"]


def test_plain_profile_publishes_on_loopback_only():
    (port,) = services()["learner"]["ports"]
    assert interpolate(str(port)) == f"127.0.0.1:{LEARNER_PORT}:{LEARNER_PORT}"
    (port,) = services()["evaluator"]["ports"]
    assert interpolate(str(port)) == "127.0.0.1:8080:8080"


def test_gpu_profile_gives_the_learner_a_gpu_and_only_it():
    with open(REPO / "compose.gpu.yaml") as f:
        override = yaml.safe_load(f)["services"]
    assert set(override) == {"learner"}, "actors and the evaluator stay on the CPU"
    (device,) = override["learner"]["deploy"]["resources"]["reservations"]["devices"]
    assert device["capabilities"] == ["gpu"] and device["driver"] == "nvidia"
    text = (REPO / "compose.gpu.yaml").read_text()
    assert "TORCH=cuda" in text, "the file says how to build the CUDA image it needs"
    client = compose_client()
    if client is not None:  # the compose client merges the two files without complaint
        proc = subprocess.run(client + ["-f", str(COMPOSE), "-f", str(REPO / "compose.gpu.yaml"), "config", "-q"],
                              capture_output=True, text=True, cwd=REPO)
        assert proc.returncode == 0, proc.stderr
