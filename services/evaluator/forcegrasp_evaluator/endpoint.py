"""The evaluator's best-policy endpoint: a Zenoh queryable, a read-only HTTP server, and clients.

Zenoh: ``forcegrasp/<run>/best`` answers a query with one ``best`` message (msgpack, protocol
version 1, fields in :func:`encode_best` and ``docs/evaluator.md``) carrying the policy file's
bytes and its scores. A query with parameters or a payload, or one that arrives before any
checkpoint was evaluated, gets an *error reply* whose payload is a UTF-8 JSON object
``{"error": "..."}``. A run nobody evaluates gets no reply at all (Zenoh has nobody to ask).

HTTP (stdlib ``http.server``, one thread per request, GET and HEAD only):

=================  =====================================================================
``/``              the routes, as JSON
``/best``          the best policy's metadata (JSON; with several objects their table, ``objects``)
``/best/policy``   the best policy file (``application/octet-stream`` download); headers
                   ``X-ForceGrasp-Sha256`` and ``X-ForceGrasp-Meta`` (the metadata, JSON)
``/top``           the top-k index (JSON, without the evaluation history; per member ``objects``)
=================  =====================================================================

Everything is served from an in-memory snapshot the service replaces after each change, so a
request can never name a file: no path is ever mapped to the disk. Any other path is a 404, a
path with ``..``, ``//``, backslashes or percent-encoding a 404 that says why, any other method a
405, a query other than ``?run=<this run>`` a 400 or 404; every error body is JSON
``{"error": ...}``. ``?run=NAME`` lets a client check it talks to the right run.

Bounds: a request with a body is a 413 (nothing here takes one; http.server already caps the
request line at 64 KiB and the headers at 100); each client address gets ``RATE_PER_S`` requests
a second with bursts of ``BURST`` (then 429 with ``Retry-After``); at most ``MAX_CONNECTIONS``
connections are served at once, the others are closed unanswered. All counted by status.
"""

from __future__ import annotations

import hashlib
import json
import logging
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Callable

from forcegrasp.policy_file import PolicyFileError, load_policy_bytes
from forcegrasp.protocol import Keys, ProtocolError
from forcegrasp.protocol.best import BestPolicy, decode_best, encode_best

log = logging.getLogger("forcegrasp.evaluator")

# --------------------------------------------------------------------------------------------
# What the endpoints serve: one immutable snapshot, swapped whole
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Snapshot:
    run: str
    best: BestPolicy | None
    reply: bytes | None        # encoded ``best`` message
    best_json: bytes           # /best body
    top_json: bytes            # /top body

    @classmethod
    def build(cls, run: str, best: BestPolicy | None, top: dict) -> "Snapshot":
        reply = encode_best(best) if best is not None else None
        meta = best.metadata() if best is not None else None
        if meta is not None:
            meta["policy_url"] = "/best/policy"
            objects = next((m.get("objects") for m in top.get("members", []) if m.get("best")), None)
            if objects:  # a run of several objects: the best's ranking figures per object
                meta["objects"] = objects
        return cls(run, best, reply, _json(meta) if meta else b"", _json(top))


def _json(obj) -> bytes:
    return (json.dumps(obj, indent=1, allow_nan=False) + "\n").encode()


def error_json(message: str, **extra) -> bytes:
    return _json({"error": message, **extra})


# --------------------------------------------------------------------------------------------
# Zenoh queryable
# --------------------------------------------------------------------------------------------

def declare_best_queryable(session, run: str, snapshot: Callable[[], Snapshot], on_query=None):
    """Answer ``forcegrasp/<run>/best``; runs on Zenoh's thread, so it only reads the snapshot."""
    key = Keys(run).best

    def on(query) -> None:
        outcome = "ok"
        try:
            params = str(query.parameters)
            payload = query.payload
            snap = snapshot()
            if params:
                outcome = "malformed"
                query.reply_err(error_json(f"{key} takes no parameters (got {params[:200]!r})"))
            elif payload is not None and len(payload.to_bytes()) > 0:
                outcome = "malformed"
                query.reply_err(error_json(f"{key} takes no payload"))
            elif snap.reply is None:
                outcome = "empty"
                query.reply_err(error_json(f"run {run!r}: no checkpoint evaluated yet", run=run))
            else:
                query.reply(key, snap.reply)
        except Exception:  # never let a bad query kill Zenoh's thread
            outcome = "failed"
            log.exception("best queryable failed")
        if on_query is not None:
            on_query(outcome)

    return session.declare_queryable(key, on)


# --------------------------------------------------------------------------------------------
# HTTP server
# --------------------------------------------------------------------------------------------

ROUTES = {
    "/": "this list",
    "/best": "metadata of the best policy (JSON)",
    "/best/policy": "the best policy file (safetensors download)",
    "/top": "the top-k checkpoints and their scores (JSON)",
}


RATE_PER_S = 20.0
BURST = 40
MAX_CONNECTIONS = 32


class _Handler(BaseHTTPRequestHandler):
    server: "EvaluatorHTTPServer"
    server_version = "forcegrasp-evaluator"
    protocol_version = "HTTP/1.1"
    timeout = 10  # seconds a client may take to send its request (slow clients do not pin threads)

    # -- responses ---------------------------------------------------------------------------
    def _send(self, status: int, body: bytes, content_type: str = "application/json",
              headers: dict | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        for k, v in (headers or {}).items():
            self.send_header(k, v)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)
        self.server.count(status)

    def _error(self, status: int, message: str, **extra) -> None:
        headers = extra.pop("headers", None)
        self._send(status, error_json(message, status=status, **extra), headers=headers)

    def send_error(self, code, message=None, explain=None):
        """Errors raised by http.server itself (bad request line, header too long...) as JSON."""
        try:
            self.close_connection = True
            self._error(int(code), message or HTTPStatus(code).phrase)
        except Exception:
            pass

    def log_message(self, format, *args):  # noqa: A002 (http.server's name)
        log.debug("http %s %s", self.address_string(), format % args)

    # -- routing -----------------------------------------------------------------------------
    def do_GET(self) -> None:
        self._route()

    def do_HEAD(self) -> None:
        self._route()

    def _not_allowed(self) -> None:
        self.close_connection = True
        self._error(405, f"method {self.command} not allowed: this server is read-only (GET, HEAD)",
                    headers={"Allow": "GET, HEAD"})

    do_POST = do_PUT = do_DELETE = do_PATCH = do_OPTIONS = do_TRACE = do_CONNECT = _not_allowed

    def __getattr__(self, name: str):
        """Any other method (``FOO / HTTP/1.1``) is a 405 too, not http.server's 501."""
        if name.startswith("do_"):
            return self._not_allowed
        raise AttributeError(name)

    def _route(self) -> None:
        if not self.server.allow(self.client_address[0]):
            self.close_connection = True
            self._error(429, f"too many requests: at most {RATE_PER_S:g} a second per client", headers={"Retry-After": "1"})
            return
        length = self.headers.get("Content-Length", "0").strip() or "0"
        if not length.isdigit() or int(length) > 0 or self.headers.get("Transfer-Encoding"):
            self.close_connection = True
            self._error(413, "requests here have no body")
            return
        raw = self.path
        path, _, query = raw.partition("?")
        if not path.startswith("/") or "%" in path or "\\" in path or "//" in path \
                or any(seg in (".", "..") for seg in path.split("/")):
            self._error(404, "no such resource: paths are plain names like /best (no '..', '//', "
                             "backslashes or percent-encoding)", path=raw[:200])
            return
        if path != "/" and path.endswith("/"):
            path = path[:-1]
        if path not in ROUTES:
            self._error(404, f"no such resource {path[:200]!r}", routes=sorted(ROUTES))
            return
        try:
            params = urllib.parse.parse_qs(query, keep_blank_values=True, strict_parsing=bool(query),
                                           max_num_fields=4)
        except ValueError:
            self._error(400, "malformed query string", query=query[:200])
            return
        snap = self.server.snapshot()
        unknown = sorted(set(params) - {"run"})
        if unknown or any(len(v) != 1 for v in params.values()):
            self._error(400, f"unknown or repeated query parameters {unknown or sorted(params)}; "
                             "the only one is run=<run name>")
            return
        if "run" in params and params["run"][0] != snap.run:
            self._error(404, f"unknown run {params['run'][0][:128]!r}: this evaluator serves run {snap.run!r}",
                        run=snap.run)
            return
        if path == "/":
            self._send(200, _json({"run": snap.run, "routes": ROUTES}))
        elif path == "/top":
            self._send(200, snap.top_json)
        elif snap.best is None:
            self._error(503, f"run {snap.run!r}: no checkpoint evaluated yet", run=snap.run,
                        headers={"Retry-After": "30"})
        elif path == "/best":
            self._send(200, snap.best_json)
        else:  # /best/policy
            b = snap.best
            self._send(200, b.policy, "application/octet-stream", headers={
                "Content-Disposition": f'attachment; filename="{b.run}-best-{b.step:09d}.safetensors"',
                "ETag": f'"{b.sha256}"',
                "X-ForceGrasp-Sha256": b.sha256,
                "X-ForceGrasp-Meta": json.dumps(b.metadata(), ensure_ascii=True, allow_nan=False),
            })


class EvaluatorHTTPServer(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, host: str, port: int, snapshot: Callable[[], Snapshot]):
        super().__init__((host, port), _Handler)
        self.snapshot = snapshot
        self.requests_by_status: dict[str, int] = {}
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._buckets: dict[str, tuple[float, float]] = {}  # client address -> (tokens, time)
        self.max_connections = MAX_CONNECTIONS
        self.connections = 0  # connections holding a slot now (each has a handler thread)

    def allow(self, client: str) -> bool:
        """Token bucket per client address (`RATE_PER_S`, `BURST`)."""
        now = time.monotonic()
        with self._lock:
            if len(self._buckets) > 4096:  # forget idle clients: the table stays bounded
                self._buckets = {k: v for k, v in self._buckets.items() if now - v[1] < 10.0}
            tokens, last = self._buckets.get(client, (float(BURST), now))
            tokens = min(float(BURST), tokens + (now - last) * RATE_PER_S)
            ok = tokens >= 1.0
            self._buckets[client] = (tokens - 1.0 if ok else tokens, now)
            return ok

    def process_request(self, request, client_address):
        with self._lock:
            free = self.connections < self.max_connections
            self.connections += free
        if not free:  # every slot busy: close, do not queue a thread
            self.count(503)
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except Exception:
            self._release()
            raise

    def process_request_thread(self, request, client_address):
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._release()

    def _release(self) -> None:
        with self._lock:
            self.connections -= 1

    @property
    def port(self) -> int:
        return self.server_address[1]

    def count(self, status: int) -> None:
        with self._lock:
            key = str(status)
            self.requests_by_status[key] = self.requests_by_status.get(key, 0) + 1

    def start(self) -> "EvaluatorHTTPServer":
        self._thread = threading.Thread(target=self.serve_forever, kwargs={"poll_interval": 0.25},
                                        name="evaluator-http", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self.shutdown()
        self.server_close()
        if self._thread is not None:
            self._thread.join(timeout=5)


# --------------------------------------------------------------------------------------------
# Clients (``forcegrasp best``)
# --------------------------------------------------------------------------------------------

class BestFetchError(RuntimeError):
    """The best policy could not be fetched; the message says why and what to check."""


def fetch_best_zenoh(session, run: str, timeout: float = 10.0) -> BestPolicy:
    """Ask ``forcegrasp/<run>/best`` until an evaluator answers or ``timeout`` passes."""
    key = Keys(run).best
    deadline = time.monotonic() + timeout
    while True:
        remaining = deadline - time.monotonic()
        for reply in session.get(key, timeout=max(0.2, min(1.0, remaining))):
            if reply.ok is not None:
                try:
                    return decode_best(reply.ok.payload.to_bytes())
                except ProtocolError as exc:
                    raise BestFetchError(f"malformed reply on {key}: {exc}") from None
            message = reply.err.payload.to_bytes().decode("utf-8", "replace")
            try:
                message = json.loads(message)["error"]
            except (ValueError, KeyError, TypeError):
                pass
            raise BestFetchError(f"the evaluator of run {run!r} answered with an error: {message}")
        if time.monotonic() >= deadline:
            break
    others = _evaluator_runs(session)
    hint = (f" Evaluators are running for: {', '.join(sorted(others))}." if others and run not in others
            else " Is the evaluator running and connected (network.connect), or use --url with its HTTP address?")
    raise BestFetchError(f"no evaluator answered on {key} within {timeout:.0f} s (unknown run {run!r}?).{hint}")


def _evaluator_runs(session) -> set[str]:
    runs = set()
    try:
        for reply in session.liveliness().get("forcegrasp/*/alive/evaluator/*", timeout=1.0):
            if reply.ok is not None:
                runs.add(str(reply.ok.key_expr).split("/")[1])
    except Exception:  # only a hint for the error message
        pass
    return runs


def fetch_best_http(url: str, run: str | None = None, timeout: float = 10.0) -> BestPolicy:
    """GET ``<url>/best/policy`` and check it (SHA-256 header, policy file, metadata)."""
    base = url.rstrip("/")
    if not base.startswith(("http://", "https://")):
        raise BestFetchError(f"--url must start with http:// or https://, got {url!r}")
    target = f"{base}/best/policy" + (f"?run={urllib.parse.quote(run)}" if run else "")
    try:
        with urllib.request.urlopen(target, timeout=timeout) as resp:
            data = resp.read()
            sha = resp.headers.get("X-ForceGrasp-Sha256", "")
            meta_text = resp.headers.get("X-ForceGrasp-Meta", "")
    except urllib.error.HTTPError as exc:
        body = exc.read().decode("utf-8", "replace")
        try:
            body = json.loads(body)["error"]
        except (ValueError, KeyError, TypeError):
            body = body[:200]
        raise BestFetchError(f"{target}: HTTP {exc.code}: {body}") from None
    except (urllib.error.URLError, OSError) as exc:
        raise BestFetchError(f"{target}: cannot connect ({getattr(exc, 'reason', exc)}); is the evaluator running?") from None
    try:
        meta = json.loads(meta_text)
        best = BestPolicy(**{k: meta[k] for k in BestPolicy.__dataclass_fields__ if k != "policy"}, policy=data)
    except (ValueError, KeyError, TypeError) as exc:
        raise BestFetchError(f"{target}: malformed reply (metadata header: {exc})") from None
    if hashlib.sha256(data).hexdigest() != sha or sha != best.sha256:
        raise BestFetchError(f"{target}: malformed reply (the file's SHA-256 does not match its header)")
    try:
        load_policy_bytes(data, source=target)
    except PolicyFileError as exc:
        raise BestFetchError(f"malformed reply: {exc}") from None
    return best
