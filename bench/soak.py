"""Soak: the local cluster under actor churn and one learner restart, watched for crashes, memory
growth and throughput loss. About 10 minutes; not in CI.

The fault tests show each fault survived once; a soak shows that surviving it a hundred times leaks
nothing. Real processes on loopback, in a new temporary run folder on a free port (it never meets
another cluster, and ends only the processes it started, by PID): the learner, the evaluator and
``--actors`` actors from `forcegrasp up`'s commands, at tiny settings with a small replay buffer
(``--buffer``) that is full early. Every ``--churn-s`` seconds one actor is killed (SIGKILL and
SIGTERM in turn) and replaced by one with a new id and seed; actor-0 is never churned, it is the
long-lived actor whose memory is watched. Halfway, the learner gets SIGTERM (it checkpoints) and is
started again (it resumes). Each process's VmRSS (/proc/<pid>/status) is sampled every second; the
learner's ``ingested`` counter comes from its stats messages on Zenoh.

Checks, printed and written to ``--out``, exit status 1 if one fails: no service exited unasked and
every one asked to stop exited cleanly; after the buffer is full, the RSS slope (MB/min) and last-
vs first-minute change of every long-lived process; the ingest rate in the ``--window-s`` after each
churn vs the one before; the restarted learner resumed at its checkpoint and went on ingesting.

    python bench/soak.py --minutes 10 --out soak.json --plot soak.png
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from forcegrasp.cli.up import service_commands
from forcegrasp.config import load_config
from forcegrasp.protocol import Keys, ProtocolError, decode_stats
from forcegrasp.rundir import RunDir
from forcegrasp.runtime import open_service_session
from forcegrasp.supervisor import GRACE_S, stop_all
from forcegrasp.transport import QueueSubscriber, close_session, free_tcp_port

RUN = "soak"
TINY = ["env.object=camera", "actor.envs_per_actor=2", "actor.random_steps=200", "actor.publish_batch=32",
        "network.lease_ms=1000", "learner.stats_every_s=1.0", "learner.checkpoint_every=2000",
        "learner.broadcast_every=50", "learner.sac.learning_starts=500", "learner.sac.hidden=[64, 64]",
        "learner.sac.batch_size=64", "learner.sac.num_threads=1", "evaluator.eval_every=2000",
        "evaluator.eval_episodes=2", "evaluator.final_rank_episodes=4", "evaluator.http_port=0"]
SETTLE_S = 30.0  # after a start (imports, replay load), the buffer filling or the learner restart: not steady yet


def rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except (OSError, ValueError):
        pass
    return None


@dataclass
class Proc:
    label: str
    cmd: list[str]
    popen: subprocess.Popen
    started: float
    churned: bool = False  # short-lived by design: reported, not checked for flat memory
    signalled: str | None = None
    signalled_at: float | None = None
    rss: list = field(default_factory=list)  # (t, MB)


class Soak:
    def __init__(self, args):
        self.args = args
        root = Path(tempfile.mkdtemp(prefix="forcegrasp-soak-"))
        overrides = [f"run.name={RUN}", f"run.output_dir={root}", f"learner.sac.buffer_size={args.buffer}",
                     f'network.learner_listen=["tcp/127.0.0.1:{free_tcp_port()}"]', *TINY, *args.overrides]
        self.config = load_config(env={}, overrides=overrides)  # this shell's FORCEGRASP_* do not apply
        self.files = RunDir.of(self.config)
        self.files.logs.mkdir(parents=True, exist_ok=True)
        self.files.cluster_config.write_text(self.config.to_toml())
        self.commands = service_commands(self.files.cluster_config, args.actors, True, self.config.run.seed)
        self.env = {k: v for k, v in os.environ.items() if not k.startswith("FORCEGRASP_")}
        self.t0 = time.monotonic()
        self.procs: dict[str, Proc] = {}  # slot -> its live process
        self.everyone: list[Proc] = []
        self.stopping: list[tuple[Proc, float]] = []  # signalled, exit not yet collected
        self.events: list[dict] = []
        self.learner: list[tuple[float, int, int]] = []  # (t, ingested, replay size)
        self.crashes, self.unclean, self.early, self.restart = [], [], [], {}
        self.actor_ids: set[str] = set()  # every actor the learner has heard from
        self.full_t: float | None = None
        self.churns, self.next_actor = 0, args.actors

    def now(self) -> float:
        return time.monotonic() - self.t0

    def event(self, kind: str, text: str, show: bool = True) -> None:
        self.events.append({"t": round(self.now(), 2), "kind": kind, "text": text})
        if show:
            print(f"[{self.now():5.0f}s] {text}", flush=True)

    # ------------------------------------------------------------------ processes
    def start(self, slot: str, label: str, cmd: list[str], churned: bool = False) -> None:
        with open(self.files.log(label), "ab") as log:
            popen = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True, env=self.env)
        self.procs[slot] = Proc(label, cmd, popen, self.now(), churned)
        self.everyone.append(self.procs[slot])

    def send(self, slot: str, sig: signal.Signals) -> Proc:
        p = self.procs.pop(slot)
        p.signalled, p.signalled_at = sig.name, self.now()
        p.popen.send_signal(sig)
        self.stopping.append((p, self.now()))
        return p

    def exited(self, p: Proc) -> None:
        """A process we stopped should exit 0. A churned actor signalled while still starting up (its
        handler not installed yet: it dies of the signal, or of KeyboardInterrupt inside an import)
        is counted apart. Anything else is an unclean stop."""
        code, sig = p.popen.returncode, signal.Signals[p.signalled]
        starting = p.signalled_at is not None and p.signalled_at - p.started < SETTLE_S / 3
        if p.churned and code != 0 and sig != signal.SIGKILL and (code == -sig or starting):
            self.early.append(p.label)
        elif code != 0 and sig != signal.SIGKILL:
            self.unclean.append({"service": p.label, "pid": p.popen.pid, "signal": p.signalled, "exit": code})

    def reap(self) -> None:
        """Collect exit codes of the processes told to stop; restart any that exited unasked."""
        for p, since in list(self.stopping):
            if p.popen.poll() is None and self.now() - since > GRACE_S:
                p.popen.kill()  # returncode -9, signalled SIGTERM: counted unclean
                p.popen.wait()
            if p.popen.poll() is not None:
                self.stopping.remove((p, since))
                self.exited(p)
        for slot, p in list(self.procs.items()):
            if p.popen.poll() is not None:
                self.crashes.append({"service": p.label, "pid": p.popen.pid, "exit": p.popen.returncode})
                self.event("crash", f"{p.label} (pid {p.popen.pid}) exited unasked ({p.popen.returncode}); restarted")
                self.start(slot, p.label + "-again", p.cmd, p.churned)

    def churn(self) -> None:
        slots = sorted(s for s in self.procs if s.startswith("actor-") and s != "actor-0")
        sig = signal.SIGKILL if self.churns % 2 == 0 else signal.SIGTERM
        slot, k = slots[self.churns % len(slots)], self.next_actor
        old = self.send(slot, sig).label
        cmd = service_commands(self.files.cluster_config, k + 1, False, self.config.run.seed)[f"actor-{k}"]
        self.start(slot, f"actor-{k}", cmd, churned=True)  # the launcher's id and seed for actor k
        self.churns, self.next_actor = self.churns + 1, k + 1
        self.event(sig.name, f"{sig.name} {old}, started actor-{k}", show=False)

    def restart_learner(self) -> None:
        before = self.learner[-1][1] if self.learner else 0
        self.event("restart", f"learner: SIGTERM at {before} ingested (it checkpoints), then started again")
        p = self.send("learner", signal.SIGTERM)
        try:
            p.popen.wait(timeout=3 * GRACE_S)
        except subprocess.TimeoutExpired:
            p.popen.kill()  # counted unclean by reap()
            p.popen.wait()
        self.reap()
        self.restart = {"t_stop": round(self.now(), 2), "ingested_before": before, "wall": time.time()}
        self.start("learner", "learner-restarted", self.commands["learner"])

    # ------------------------------------------------------------------ measurements
    def drain(self, sub: QueueSubscriber) -> None:
        while (payload := sub.get(timeout=0)) is not None:
            try:
                s = decode_stats(payload)
            except ProtocolError:
                continue
            if self.restart and s.time < self.restart["wall"]:
                continue  # the stopped learner's last reports, still in flight
            v = s.values
            if self.restart and "resumed_at" not in self.restart:
                self.restart.update(resumed_at=v["ingested"], checkpoint=v["last_checkpoint"], t_back=self.now())
            self.learner.append((round(self.now(), 2), v["ingested"], v["replay_size"]))
            self.actor_ids.update(v["actors"])
            if self.full_t is None and v["replay_size"] >= self.args.buffer:
                self.full_t = self.now()
                self.event("full", f"replay buffer full ({self.args.buffer}): memory is watched from here")

    def sample_rss(self) -> None:
        for p in self.procs.values():
            mb = rss_mb(p.popen.pid)
            if mb is not None:
                p.rss.append((round(self.now(), 2), round(mb, 1)))

    def rate(self, a: float, b: float) -> float | None:
        """Transitions ingested per second over [a, b], from the learner's counter."""
        if len(self.learner) < 2 or b <= a or a < self.learner[0][0] or b > self.learner[-1][0]:
            return None
        t, n = np.array(self.learner)[:, :2].T
        return float((np.interp(b, t, n) - np.interp(a, t, n)) / (b - a))

    def progress(self) -> None:
        t, ingested, replay = self.learner[-1] if self.learner else (0.0, 0, 0)
        r = self.rate(max(t - 10, self.learner[0][0]), t) if self.learner else None
        rss = "  ".join(f"{p.label} {p.rss[-1][1]:.0f}" for p in self.procs.values() if p.rss)
        print(f"[{self.now():5.0f}s] ingested {ingested} ({'-' if r is None else f'{r:.0f}'}/s)  replay {replay}/"
              f"{self.args.buffer}  churns {self.churns}  crashes {len(self.crashes)}  RSS MB: {rss}", flush=True)

    # ------------------------------------------------------------------ the run
    def run(self) -> None:
        args, end = self.args, self.args.minutes * 60
        session = sub = None
        try:
            for name, cmd in self.commands.items():
                self.start(name, name, cmd, churned=name.startswith("actor-") and name != "actor-0")
                if name == "learner":
                    time.sleep(0.5)  # as `forcegrasp up`: actors connect faster when the learner listens
            print(f"soak: {args.minutes:g} min, learner + evaluator + {args.actors} actors, churn every "
                  f"{args.churn_s:g} s, buffer {args.buffer}; run folder {self.files.root}", flush=True)
            session = open_service_session(self.config, "monitor")
            sub = QueueSubscriber(session, Keys(RUN).stats("learner", "0"), maxsize=4096, put_timeout=0.0)
            next_churn, next_rss, next_line = None, 0.0, 10.0
            while self.now() < end:
                self.drain(sub)
                self.reap()
                t = self.now()
                if t >= next_rss:
                    self.sample_rss()
                    next_rss = t + 1.0
                if next_churn is None and self.learner and self.learner[-1][1] > 0:
                    next_churn = t + args.churn_s  # churn once transitions flow
                if next_churn is not None and t >= next_churn:
                    self.churn()
                    next_churn = self.now() + args.churn_s
                if not self.restart and t >= end / 2:
                    self.restart_learner()
                if t >= next_line:
                    self.progress()
                    next_line = t + 10.0
                time.sleep(0.1)
            self.drain(sub)
        finally:
            if sub is not None:
                sub.close()
            close_session(session)
            print("stopping: SIGINT to every service (the learner checkpoints)", flush=True)
            for p in self.procs.values():
                p.signalled, p.signalled_at = "SIGINT", self.now()  # stop_all's
            last = [*self.procs.values(), *(p for p, _ in self.stopping)]
            stop_all({f"{p.label} (pid {p.popen.pid})": p.popen for p in last})
            for p in last:
                self.exited(p)

    # ------------------------------------------------------------------ checks
    def steady_from(self, p: Proc) -> float:
        """Memory is watched once the buffer is full, the process settled, and the learner restart too
        if the process lived through it (the actors' outboxes fill while the learner is away)."""
        t, back = max(self.full_t, p.started + SETTLE_S), self.restart.get("t_back")
        if back is not None and p.started < back and p.rss and p.rss[-1][0] > back:
            t = max(t, back + SETTLE_S)
        return t

    def memory(self) -> dict:
        if self.full_t is None:
            return {"ok": False, "why": "the replay buffer never filled: lower --buffer or run longer"}
        rows = [rss_trend(p, self.steady_from(p)) for p in self.everyone if not p.churned]
        for r in rows:
            if "slope_mb_per_min" in r:
                r["ok"] = r["slope_mb_per_min"] <= self.args.max_slope and r["change"] <= self.args.max_growth
        churned = [p for p in self.everyone if p.churned]
        measured = [r["ok"] for r in rows if "ok" in r]
        return {"ok": bool(measured) and all(measured), "buffer_full_at_s": round(self.full_t, 1), "processes": rows,
                "churned_actors": {"processes": len(churned), "reached_learner": len(self.actor_ids - {"actor-0"}),
                                   "rss_mb_max": max((x[1] for p in churned for x in p.rss), default=None)}}

    def throughput(self) -> dict:
        """Ingest rate in the window after each churn over the window before, and the same ratio at
        placebo times halfway between churns: on 2 shared cores the rate swings by a quarter from one
        15 s window to the next whatever happens, so a churn counts as harmless when its ratios look
        like the placebo's and their median is within ``--tol`` of 1."""
        a, r = self.args, self.restart
        span = (r["t_stop"] - a.window_s, r.get("t_back", 1e9) + SETTLE_S + a.window_s) if r else (1e9, 1e9)
        steady = 1e9 if self.full_t is None else self.full_t + SETTLE_S  # the early backlog worked off

        def ratio_at(tc: float) -> float | None:
            if tc - a.window_s < steady or (span[0] < tc + a.window_s and tc - a.window_s < span[1]):
                return None  # before steady state, or it would measure the learner restart
            before, after = self.rate(tc - a.window_s, tc), self.rate(tc, tc + a.window_s)
            return round(after / before, 3) if before and after is not None else None

        rows, placebo = [], []
        for e in self.events:
            if e["kind"] in ("SIGKILL", "SIGTERM") and (x := ratio_at(e["t"])) is not None:
                rows.append({"t": e["t"], "signal": e["kind"], "ratio": x})
            if e["kind"] in ("SIGKILL", "SIGTERM") and (x := ratio_at(e["t"] + a.churn_s / 2)) is not None:
                placebo.append(x)
        ratios = [x["ratio"] for x in rows]
        med = float(np.median(ratios)) if rows else None
        med_placebo = float(np.median(placebo)) if placebo else None
        return {"ok": bool(rows) and med >= 1 - a.tol and med >= med_placebo - a.tol / 2, "measured": len(rows),
                "ratio_min": min(ratios, default=None), "ratio_median": med,
                "below": sum(x < 1 - a.tol for x in ratios), "placebo_median": med_placebo,
                "placebo_min": min(placebo, default=None), "placebo_below": sum(x < 1 - a.tol for x in placebo),
                "churns": rows}

    def recovery(self) -> dict:
        r = {k: v for k, v in self.restart.items() if k != "wall"}
        if "resumed_at" not in r:
            return {"ok": False, "why": "no restart, or the restarted learner never reported", **r}
        rising = next((t for t, n, _ in self.learner if t >= r["t_back"] and n > r["resumed_at"]), None)
        r.update(ingesting_again_after_s=None if rising is None else round(rising - r["t_stop"], 1),
                 final_ingested=self.learner[-1][1], t_back=round(r["t_back"], 2))
        r["ok"] = r["checkpoint"] >= r["ingested_before"] > 0 and r["resumed_at"] >= r["checkpoint"] and bool(rising)
        return r

    def report(self) -> dict:
        checks = {"no_crash": {"ok": not self.crashes and not self.unclean, "crashes": self.crashes,
                               "unclean_stops": self.unclean, "died_of_signal_while_starting": self.early},
                  "memory_flat": self.memory(), "throughput_after_churn": self.throughput(),
                  "learner_restart": self.recovery()}
        return {**{k: getattr(self.args, k) for k in ("minutes", "actors", "churn_s", "buffer", "window_s", "tol",
                                                     "max_slope", "max_growth")},
                "churns": self.churns, "run_folder": str(self.files.root), "checks": checks, "events": self.events,
                "learner": self.learner, "rss": [{"label": p.label, "pid": p.popen.pid, "churned": p.churned,
                                                  "exit": p.popen.returncode, "samples": p.rss} for p in self.everyone]}


def rss_trend(p: Proc, since: float) -> dict:
    """Least-squares slope (MB/min) and last- vs first-minute change of one process's RSS."""
    pts = np.array([x for x in p.rss if x[0] >= since]).reshape(-1, 2)
    row = {"label": p.label, "pid": p.popen.pid}
    if len(pts) < 2 or pts[-1, 0] - pts[0, 0] < 30:
        return {**row, "why": "under 30 s of steady samples (buffer full, settled)"}
    t, mb = pts.T
    w = min(60.0, (t[-1] - t[0]) / 3)  # a minute, or a third of a short run
    first, last = float(mb[t <= t[0] + w].mean()), float(mb[t >= t[-1] - w].mean())
    slope = round(float(np.polyfit(t / 60, mb, 1)[0]), 3) + 0.0  # + 0.0: no "-0.00"
    return {**row, "seconds": int(t[-1] - t[0]), "slope_mb_per_min": slope,
            "first_mb": round(first, 1), "last_mb": round(last, 1), "change": round((last - first) / first, 4)}


def summary(rep: dict) -> str:
    c, mark = rep["checks"], lambda ok: "PASS" if ok else "FAIL"
    crash, mem, thr, rs = c["no_crash"], c["memory_flat"], c["throughput_after_churn"], c["learner_restart"]
    out = [f"soak: {rep['minutes']:g} min, {rep['actors']} actors, {rep['churns']} churns, one learner restart; "
           f"logs in {rep['run_folder']}/logs",
           f"{mark(crash['ok'])}  no crash: {len(crash['crashes'])} exits unasked, {len(crash['unclean_stops'])} "
           f"unclean stops ({len(crash['died_of_signal_while_starting'])} churned actors signalled while starting)",
           f"{mark(mem['ok'])}  memory flat (<= {rep['max_slope']:g} MB/min, <= {rep['max_growth']:+.0%}) "
           + (f"after the buffer filled at {mem['buffer_full_at_s']:.0f} s:" if "processes" in mem else mem["why"])]
    for r in mem.get("processes", []):
        out.append(f"      {r['label']:<18} pid {r['pid']:<7} " + (r.get("why") or (
            f"{r['slope_mb_per_min']:+.2f} MB/min over {r['seconds']} s, first {r['first_mb']:.0f} MB, "
            f"last {r['last_mb']:.0f} MB ({r['change']:+.1%})" + ("" if r["ok"] else "  <- too much"))))
    if mem.get("churned_actors", {}).get("processes"):
        ch = mem["churned_actors"]
        out.append(f"      churned actors: {ch['processes']} processes, {ch['reached_learner']} reached the learner, "
                   f"at most {ch['rss_mb_max']:.0f} MB (not checked)")
    out.append(f"{mark(thr['ok'])}  ingest rate {rep['window_s']:g} s after / before a churn, median >= "
               f"{1 - rep['tol']:.2f} and like the placebo's (halfway between churns): "
               + (f"{thr['measured']} churns, median {thr['ratio_median']:.2f}, min {thr['ratio_min']:.2f}, "
                  f"{thr['below']} below {1 - rep['tol']:.2f}; placebo median {thr['placebo_median']:.2f}, min "
                  f"{thr['placebo_min']:.2f}, {thr['placebo_below']} below" if thr["measured"] else "no churn measurable"))
    out.append(f"{mark(rs['ok'])}  learner restart: " + (rs.get("why") or (
        f"stopped at {rs['ingested_before']}, checkpoint {rs['checkpoint']}, resumed at {rs['resumed_at']}, "
        f"ingesting again {rs['ingesting_again_after_s']} s after the stop, final {rs['final_ingested']}")))
    return "\n".join(out)


def plot(rep: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (top, bottom) = plt.subplots(2, 1, sharex=True, figsize=(11, 7))
    for p in (p for p in rep["rss"] if p["samples"]):
        t, mb = zip(*p["samples"])
        top.plot(t, mb, **({"color": "0.7", "lw": 0.6} if p["churned"] else {"lw": 1.5, "label": p["label"]}))
    top.set_ylabel("RSS, MB (churned actors grey)")
    top.legend(loc="upper left", fontsize=8)
    if len(rep["learner"]) > 5:
        t, n = np.array(rep["learner"])[:, :2].T
        grid = np.arange(t[0] + 5, t[-1], 1.0)
        bottom.plot(grid, (np.interp(grid, t, n) - np.interp(grid - 5, t, n)) / 5, color="tab:purple")
    bottom.set(ylabel="ingested / s (5 s window)", xlabel="seconds")
    style = {"SIGKILL": ("tab:red", 0.5, ":"), "SIGTERM": ("tab:blue", 0.5, ":"), "restart": ("black", 2, "-"),
             "full": ("tab:green", 1.5, "--"), "crash": ("magenta", 2, "-")}
    for e in rep["events"]:
        for ax in (top, bottom):
            ax.axvline(e["t"], color=style[e["kind"]][0], lw=style[e["kind"]][1], ls=style[e["kind"]][2], alpha=0.6)
    fig.suptitle("soak: actor churn (red SIGKILL, blue SIGTERM), learner restart (black), buffer full (green)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add = parser.add_argument
    add("--minutes", type=float, default=10.0)
    add("--actors", type=int, default=2, help="actors kept running (>= 2; actor-0 is never churned)")
    add("--churn-s", type=float, default=5.0, help="seconds between actor replacements")
    add("--buffer", type=int, default=3000, help="replay capacity (learner.sac.buffer_size)")
    add("--window-s", type=float, default=15.0, help="ingest-rate window before and after a churn")
    add("--tol", type=float, default=0.10, help="ingest rate after a churn >= (1 - tol) x before")
    add("--max-slope", type=float, default=1.0, help="RSS slope allowed after the buffer is full, MB/min")
    add("--max-growth", type=float, default=0.05, help="last- vs first-minute RSS change allowed")
    add("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
        help="extra configuration override (repeatable)")
    add("--out", default="soak.json")
    add("--plot", default=None, help="PNG of RSS and ingest rate over time")
    args = parser.parse_args()
    if args.actors < 2:
        parser.error("--actors must be >= 2: actor-0 stays, the others are churned")
    soak = Soak(args)
    soak.run()
    rep = soak.report()
    Path(args.out).write_text(json.dumps(rep, indent=1))
    if args.plot:
        plot(rep, args.plot)
    print(summary(rep) + f"\nwrote {args.out}" + (f" and {args.plot}" if args.plot else ""))
    return 0 if all(c["ok"] for c in rep["checks"].values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
