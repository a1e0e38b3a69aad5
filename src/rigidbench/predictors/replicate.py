"""A small client for Replicate's HTTP prediction API (httpx), for the hosted video models.

Protocol: ``POST {base}/v1/models/{owner}/{name}/predictions`` with ``{"input": {...}}`` and
``Prefer: wait`` creates a prediction (Replicate holds the request until it finishes or up to 60 s);
``GET {base}/v1/predictions/{id}`` is polled until its status is ``succeeded``, ``failed`` or
``canceled``; the output URL is downloaded at once (Replicate deletes outputs after an hour). Images
too large for a data URI go through ``POST {base}/v1/files`` (multipart field ``content``).

The base URL is ``$REPLICATE_BASE_URL`` or https://api.replicate.com; the token is read only from
``$REPLICATE_API_TOKEN``, sent only to the base URL's host (never with a download) and removed from
every message this module produces (httpx messages included), so no file, log line or exception
of ours carries it.

Robustness: every request has a timeout, and the example's deadline bounds the whole exchange: each socket
read and write is cut to what is left of it (a server that trickles a byte every read timeout cannot hold
a worker past it), an API request as a whole gets at most its read timeout plus ``request_timeout_s``,
and a download slower than ``min_download_bytes_per_s`` (after the first ``request_timeout_s``) is cut
off. HTTP 429 waits for ``Retry-After`` when given, else exponential backoff with jitter; 5xx and network
errors are retried with the same bounded backoff, then fail with the API's message. A creation request
is never repeated after it may have reached Replicate without an answer (a read error): that could pay
twice; ``list_predictions`` (``GET /v1/predictions``, newest first, paged by ``next``) lets the caller
find such a prediction later. Downloads are refused past a size cap, kept only if they decode as video,
and written atomically. Every failure is a ``PredictionError`` (a ``RigidBenchError``), which the predict
stage records; ``StopRequested`` is the one raised when the run is stopping (a signal) and no new request
for a prediction may be sent.

Stopping (``Deadline.stop``, set on SIGTERM or Ctrl-C): requests already in flight get ``stop_grace_s`` more
(3 s by default), then are cut off, a creation among them included (the caller has recorded its intent, so a
rerun adopts the prediction instead of paying again); pauses between polls and retries end at once and
nothing is retried. While a stop may come, socket reads wait in slices of ``STOP_POLL_S``, so a server that
holds a request (``Prefer: wait`` holds a creation up to 60 s, a stuck one longer) cannot delay the stop.

URLs that reach a message, a log line (httpx's own included) or a record go through ``public_url``: no
user information, query or fragment, credential-looking path parts replaced by [REDACTED].
"""

from __future__ import annotations

import email.utils
import json
import logging
import os
import random
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable
from urllib.parse import urljoin, urlsplit

import httpcore
import httpx

from ..atomic import umask_mode
from ..errors import PredictionError, UserError, VideoError
from ..logsafe import install_filter, public_url, remember_secret, scrub_text
from ..video import check_decodable, probe_video

log = logging.getLogger(__name__)

DEFAULT_BASE_URL = "https://api.replicate.com"
TOKEN_ENV = "REPLICATE_API_TOKEN"
BASE_URL_ENV = "REPLICATE_BASE_URL"
TERMINAL = ("succeeded", "failed", "canceled", "aborted")
_CHUNK = 1 << 16


@dataclass(frozen=True)
class ClientSettings:
    """Limits of the client (configs/models.yaml, section ``client``); see that file for each field."""

    request_timeout_s: float = 30.0
    wait_s: int = 60
    poll_interval_s: float = 2.0
    poll_max_interval_s: float = 10.0
    max_retries: int = 6
    backoff_base_s: float = 1.0
    backoff_max_s: float = 60.0
    example_timeout_s: float = 1800.0
    max_output_bytes: int = 300_000_000
    min_download_bytes_per_s: int = 16_384  # after the first request_timeout_s of a download
    stop_grace_s: float = 3.0  # after SIGTERM or Ctrl-C: how long requests in flight may still take

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class CallStats:
    """What one example's calls cost in retries (recorded in generation.json)."""

    requests: int = 0
    rate_limited: int = 0  # HTTP 429 answers retried
    server_errors: int = 0  # HTTP 5xx answers retried
    network_errors: int = 0  # connection or read failures retried

    @property
    def retries(self) -> int:
        return self.rate_limited + self.server_errors + self.network_errors


class ReplicateError(PredictionError):
    """A request to Replicate that failed for good; the message carries the API's own message."""

    def __init__(self, message: str, status_code: int | None = None):
        super().__init__(message)
        self.status_code = status_code


class StopRequested(PredictionError):
    """The run is stopping (SIGTERM or Ctrl-C): no new prediction is created and no more polls are made."""


#: while a stop is possible, socket reads wait at most this long at a time, then look at the stop again
STOP_POLL_S = 0.25


@dataclass
class Deadline:
    """The per-example time limit: every wait, request timeout and socket read is cut to what is left of
    it. ``stop``: an event the predict stage sets on SIGTERM or Ctrl-C (see ``check_stop``); once it is set,
    requests in flight get ``stop_grace`` seconds more (``cut``), pauses end at once, and nothing is retried."""

    seconds: float
    start: float = field(default_factory=time.monotonic)
    stop: threading.Event | None = None
    stop_grace: float = ClientSettings.stop_grace_s
    _stopped_at: float | None = field(default=None, init=False, repr=False)

    @property
    def end(self) -> float:
        return self.start + self.seconds

    def left(self) -> float:
        return self.seconds - (time.monotonic() - self.start)

    def check(self, what: str) -> float:
        left = self.left()
        if left <= 0:
            raise PredictionError(f"{what}: gave up after the per-example timeout of {self.seconds:g} s "
                                  "(client.example_timeout_s in models.yaml)")
        return left

    def stopping(self) -> bool:
        return self.stop is not None and self.stop.is_set()

    def check_stop(self, what: str) -> None:
        """StopRequested when the run is stopping: called before anything that could start a new payment
        or a new wait (a creation, a poll, a retry)."""
        if self.stopping():
            raise StopRequested(f"{what}: not done, the run is stopping")

    def cut(self) -> float | None:
        """When (``time.monotonic``) requests in flight are cut off because the run is stopping: ``stop_grace``
        seconds after this deadline first saw the stop; None while it is not stopping."""
        if not self.stopping():
            return None
        if self._stopped_at is None:
            self._stopped_at = time.monotonic()
        return self._stopped_at + self.stop_grace


# -- the whole exchange under the deadline ------------------------------------------------------------

_local = threading.local()


@dataclass
class _Budget:
    """What the current thread's request may still take: until ``until`` (monotonic), and at least
    ``min_rate`` bytes/s on average once ``grace`` seconds have passed (0: no rate rule); and, when the
    example's ``deadline`` has a stop, until the stop's cut (``Deadline.cut``)."""

    until: float
    reason: str
    min_rate: float = 0.0
    grace: float = 0.0
    start: float = field(default_factory=time.monotonic)
    received: int = 0
    deadline: Deadline | None = None

    def left(self, exc: type = httpcore.ReadTimeout) -> float:
        """Seconds left before the first limit; ``exc`` with its reason when one has passed."""
        now = time.monotonic()
        left = self.until - now
        if left <= 0:
            raise exc(self.reason)
        cut = self.deadline.cut() if self.deadline is not None else None
        if cut is not None:
            if cut <= now:
                raise exc(f"cut off {self.deadline.stop_grace:g} s after the run was asked to stop "
                          "(client.stop_grace_s)")
            left = min(left, cut - now)
        return left

    def timeout(self, timeout: float | None) -> float:
        """The timeout of the next socket read: ``timeout`` cut to what is left; at most STOP_POLL_S while a
        stop may come (the read is then a slice of the wait, see ``_BudgetStream.read``)."""
        left = self.left()
        elapsed = time.monotonic() - self.start
        if self.min_rate and elapsed > self.grace and self.received < self.min_rate * elapsed:
            raise httpcore.ReadTimeout(f"the transfer is slower than the minimum of {self.min_rate:,.0f} bytes/s "
                                       f"({self.received:,} bytes in {elapsed:.1f} s; "
                                       "client.min_download_bytes_per_s)")
        if self.deadline is not None and self.deadline.stop is not None:
            left = min(left, STOP_POLL_S)
        return left if timeout is None else min(timeout, left)


class _BudgetStream:
    """A network stream whose reads and writes obey the calling thread's budget (see ``_Budget``)."""

    def __init__(self, inner):
        self._inner = inner

    def read(self, max_bytes: int, timeout: float | None = None) -> bytes:
        """Wait up to ``timeout`` for data, in slices (``_Budget.timeout``): a slice that ends without data
        reads on (a timed-out recv consumes nothing) until the caller's timeout or a budget limit passes."""
        budget = getattr(_local, "budget", None)
        if budget is None:
            return self._inner.read(max_bytes, timeout)
        end = None if timeout is None else time.monotonic() + timeout
        while True:
            wanted = None if end is None else end - time.monotonic()
            if wanted is not None and wanted <= 0:
                raise httpcore.ReadTimeout("timed out")
            try:
                data = self._inner.read(max_bytes, budget.timeout(wanted))
            except httpcore.ReadTimeout:
                budget.timeout(None)  # our own reason when the budget (or the stop) is what ran out
                continue  # else a slice, or the caller's timeout (raised above)
            budget.received += len(data)
            return data

    def write(self, buffer: bytes, timeout: float | None = None) -> None:
        budget = getattr(_local, "budget", None)
        if budget is not None:
            left = budget.left(httpcore.WriteTimeout)
            timeout = left if timeout is None else min(timeout, left)
        self._inner.write(buffer, timeout)

    def start_tls(self, *args, **kwargs):
        return _BudgetStream(self._inner.start_tls(*args, **kwargs))

    def close(self) -> None:
        self._inner.close()

    def get_extra_info(self, info: str):
        return self._inner.get_extra_info(info)


class _BudgetBackend:
    """httpcore's network backend with every stream wrapped in ``_BudgetStream``."""

    def __init__(self, inner):
        self._inner = inner

    def connect_tcp(self, *args, **kwargs):
        return _BudgetStream(self._inner.connect_tcp(*args, **kwargs))

    def connect_unix_socket(self, *args, **kwargs):
        return _BudgetStream(self._inner.connect_unix_socket(*args, **kwargs))

    def sleep(self, seconds: float) -> None:
        self._inner.sleep(seconds)


def _budget_transport(limits: httpx.Limits) -> httpx.HTTPTransport:
    """httpx's transport with ``_BudgetBackend`` under its connection pool (httpcore >= 1.0 keeps the backend
    as ``_network_backend``; if a later version does not, the per-chunk checks of downloads still apply)."""
    transport = httpx.HTTPTransport(limits=limits, trust_env=False)
    pool = getattr(transport, "_pool", None)
    backend = getattr(pool, "_network_backend", None)
    if backend is not None:
        pool._network_backend = _BudgetBackend(backend)
    else:  # pragma: no cover - other httpcore versions
        log.debug("httpcore has no _network_backend; socket reads are bounded by the read timeout only")
    return transport


class _budget:
    """Context manager: the calling thread's requests obey ``_Budget(...)`` until it exits."""

    def __init__(self, budget: _Budget):
        self.budget = budget

    def __enter__(self) -> _Budget:
        self.previous = getattr(_local, "budget", None)
        _local.budget = self.budget
        return self.budget

    def __exit__(self, *exc) -> None:
        _local.budget = self.previous


def _limit(deadline: Deadline, seconds: float, what: str) -> _Budget:
    """The budget of one request: ``seconds`` from now, or the example's deadline if that comes first (and the
    deadline's stop, ``Deadline.cut``)."""
    until = time.monotonic() + seconds
    if deadline.end <= until:
        return _Budget(deadline.end, f"{what}: stopped at the per-example timeout of {deadline.seconds:g} s "
                                     "(client.example_timeout_s in models.yaml), counted over the whole exchange",
                       deadline=deadline)
    return _Budget(until, f"{what}: no complete answer within {seconds:g} s (the request's read timeout plus "
                          "client.request_timeout_s)", deadline=deadline)


def base_url_from_env() -> str:
    """``$REPLICATE_BASE_URL`` (without a trailing "/" or "/v1") or Replicate's API."""
    base = os.environ.get(BASE_URL_ENV, "").strip() or DEFAULT_BASE_URL
    parts = urlsplit(base)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise UserError(f"{BASE_URL_ENV} must be an http(s) URL such as {DEFAULT_BASE_URL}, got {public_url(base)!r}")
    base = base.rstrip("/")
    return base[:-3] if base.endswith("/v1") else base


_LOG_NAMES = ("httpx", "httpcore.connection", "httpcore.http11", "httpcore.proxy", __name__,
              __name__.rpartition(".")[0] + ".hosted")
# httpx logs every request's full URL at INFO: its records and ours are scrubbed even where the command line's
# logging (logsafe.configure_logging) is not in use.
install_filter(_LOG_NAMES)


def token_from_env() -> str:
    """The API token from ``$REPLICATE_API_TOKEN``; a UserError (one line, never the token) when it is not set
    or cannot be one: API tokens are printable ASCII without spaces."""
    token = os.environ.get(TOKEN_ENV, "").strip()
    if not token:
        raise UserError(f"{TOKEN_ENV} is not set: hosted models call Replicate's API with your API token; "
                        f"export {TOKEN_ENV}=... (https://replicate.com/account/api-tokens) or use --dry-run")
    for i, ch in enumerate(token):
        if not "\x21" <= ch <= "\x7e":
            kind = ("a space or line break" if ch.isspace() else
                    "a non-ASCII character" if ord(ch) > 127 else "a control character")
            raise UserError(f"{TOKEN_ENV} holds {kind} (character {i + 1} of {len(token)}); an API token is "
                            "printable ASCII without spaces: copy it again from https://replicate.com/account/api-tokens "
                            "and export it in quotes")
    return token


def output_url(output: Any) -> str | None:
    """The video URL of a prediction's ``output``: a URL string, or the first one of a list or mapping."""
    if isinstance(output, str):
        return output
    if isinstance(output, (list, tuple)):
        for item in output:
            if (url := output_url(item)) is not None:
                return url
    if isinstance(output, dict):
        for key in ("video", "output", "url"):
            if (url := output_url(output.get(key))) is not None:
                return url
    return None


class ReplicateClient:
    """Thread-safe: one instance serves every example of a run (one connection pool)."""

    def __init__(self, settings: ClientSettings, *, base_url: str | None = None, token: str | None = None,
                 max_connections: int = 16, sleep: Callable[[float], None] | None = None):
        self.settings = settings
        self.base_url = (base_url or base_url_from_env()).rstrip("/")
        self._token = token if token is not None else token_from_env()
        remember_secret(self._token)
        self._api_host = urlsplit(self.base_url).netloc
        self._sleep = sleep  # None: time.sleep, ended early by the example's stop (``_nap``)
        self._rng = random.Random()
        self._rng_lock = threading.Lock()
        limits = httpx.Limits(max_connections=max_connections, max_keepalive_connections=max_connections)
        # No default headers: the token is added per request, to API requests only.
        self._http = httpx.Client(transport=_budget_transport(limits), follow_redirects=False, trust_env=False)

    def __repr__(self) -> str:  # never the token
        return f"ReplicateClient({public_url(self.base_url)!r})"

    def close(self) -> None:
        self._http.close()

    # -- the API -----------------------------------------------------------------------------------

    def create(self, model: str, inputs: dict[str, Any], deadline: Deadline, stats: CallStats) -> dict[str, Any]:
        """Create a prediction of official model "owner/name"; returns the prediction (finished when
        Replicate could finish it within the ``Prefer: wait`` window)."""
        owner, _, name = model.partition("/")
        url = f"{self.base_url}/v1/models/{owner}/{name}/predictions"
        wait = max(1, min(60, int(self.settings.wait_s)))
        headers = {"Prefer": "wait" if wait == 60 else f"wait={wait}"}
        response = self._request("POST", url, f"creating a {model} prediction", deadline, stats, json_body={"input": inputs},
                                 headers=headers, read_timeout=self.settings.request_timeout_s + wait, idempotent=False)
        return self._prediction(response, f"creating a {model} prediction")

    def list_predictions(self, deadline: Deadline, stats: CallStats):
        """The account's predictions, newest first, page by page (``GET /v1/predictions``, following ``next``
        on the API's host only). Yields each page's list of predictions."""
        url = f"{self.base_url}/v1/predictions"
        while True:
            response = self._request("GET", url, "listing recent predictions", deadline, stats)
            body = self._json(response, "listing recent predictions")
            results = body.get("results") if isinstance(body, dict) else None
            if not isinstance(results, list):
                raise ReplicateError("listing recent predictions: Replicate's answer has no results list")
            yield [p for p in results if isinstance(p, dict) and isinstance(p.get("id"), str)]
            nxt = body.get("next")
            if not isinstance(nxt, str) or not nxt:
                return
            url = urljoin(url, nxt)

    def get(self, prediction_id: str, deadline: Deadline, stats: CallStats) -> dict[str, Any]:
        """The prediction ``prediction_id`` as Replicate has it now (always read from the base URL)."""
        what = f"prediction {prediction_id}"
        response = self._request("GET", f"{self.base_url}/v1/predictions/{prediction_id}", what, deadline, stats)
        return self._prediction(response, what)

    def wait(self, prediction: dict[str, Any], deadline: Deadline, stats: CallStats) -> dict[str, Any]:
        """Poll until the prediction is finished (succeeded, failed or canceled)."""
        interval = self.settings.poll_interval_s
        while prediction.get("status") not in TERMINAL:
            what = f"prediction {prediction['id']} ({prediction.get('status')})"
            deadline.check_stop(f"waiting for {what}")
            self._pause(interval, deadline, what)
            deadline.check_stop(f"waiting for {what}")
            interval = min(interval * 1.5, self.settings.poll_max_interval_s)
            prediction = self.get(prediction["id"], deadline, stats)
        return prediction

    def upload(self, data: bytes, filename: str, content_type: str, deadline: Deadline, stats: CallStats) -> str:
        """Upload ``data`` through the files endpoint; returns the URL a model input may name."""
        what = f"uploading {filename}"
        response = self._request("POST", f"{self.base_url}/v1/files", what, deadline, stats,
                                 files={"content": (filename, data, content_type)})
        body = self._json(response, what)
        url = (body.get("urls") or {}).get("get") if isinstance(body, dict) else None
        if not isinstance(url, str):
            raise ReplicateError(f"{what}: Replicate's answer has no urls.get")
        return url

    def download(self, url: str, dest: Path, deadline: Deadline, stats: CallStats) -> tuple[Path, int]:
        """Download ``url`` to ``dest`` (atomically, without the token) if it is under the size cap and
        decodes as video; returns (dest, bytes)."""
        if urlsplit(url).scheme not in ("http", "https"):
            raise PredictionError(f"the output {self.scrub(public_url(url))[:80]!r} is not an http(s) URL")
        what = f"downloading {self.scrub(public_url(url))}"
        cap = self.settings.max_output_bytes
        dest = Path(dest)
        dest.parent.mkdir(parents=True, exist_ok=True)
        attempt = 0
        while True:
            left = deadline.check(what)
            stats.requests += 1
            fd, tmp_name = tempfile.mkstemp(dir=dest.parent, prefix=f".{dest.stem}.", suffix=f".part{dest.suffix}")
            tmp = Path(tmp_name)
            budget = _limit(deadline, deadline.seconds, what)  # the whole download: until the deadline ...
            budget.min_rate, budget.grace = self.settings.min_download_bytes_per_s, self.settings.request_timeout_s
            try:
                try:
                    with _budget(budget), os.fdopen(fd, "wb") as fh, self._http.stream(
                            "GET", url, timeout=self._timeout(left), follow_redirects=True) as response:
                        if response.status_code == 429 or response.status_code >= 500:
                            raise _Retry(response.status_code, _retry_after(response), self._message(response))
                        if response.status_code >= 400:
                            raise PredictionError(f"{what}: HTTP {response.status_code} "
                                                  f"{self._message(response)}")
                        declared = response.headers.get("content-length")
                        if declared is not None and declared.isdigit() and int(declared) > cap:
                            raise PredictionError(f"{what}: the output is {int(declared):,} bytes, over the cap of "
                                                  f"{cap:,} (client.max_output_bytes); refused")
                        size = 0
                        for chunk in response.iter_bytes(_CHUNK):
                            size += len(chunk)
                            if size > cap:
                                raise PredictionError(f"{what}: the output passed the cap of {cap:,} bytes "
                                                      "(client.max_output_bytes); refused")
                            fh.write(chunk)
                            if deadline.left() <= 0:
                                deadline.check(what)
                        fh.flush()
                        os.fsync(fh.fileno())
                except httpx.TransportError as exc:
                    raise _Retry(None, None, self.scrub(f"{type(exc).__name__}: {exc}")) from None
                _check_video(tmp, what)
                umask_mode(tmp)  # mkstemp makes it private; it gets the mode of every other output
                tmp.replace(dest)
                return dest, size
            except _Retry as retry:
                attempt = self._retry_or_fail(retry, attempt, what, deadline, stats)
            finally:
                if tmp.exists():
                    tmp.unlink()

    # -- plumbing ----------------------------------------------------------------------------------

    def _headers(self, extra: dict[str, str] | None = None) -> dict[str, str]:
        return {"Authorization": f"Bearer {self._token}", "User-Agent": "rigidbench", **(extra or {})}

    def _timeout(self, left: float, read: float | None = None) -> httpx.Timeout:
        t = min(self.settings.request_timeout_s, max(left, 0.001))
        return httpx.Timeout(t, read=min(read if read is not None else t, max(left, 0.001)))

    def scrub(self, text: str) -> str:
        """``text`` with every URL made public (no query, credential-looking parts redacted) and the token
        replaced by [REDACTED]."""
        return scrub_text(text, (self._token,) if self._token else ())

    def scrub_all(self, value: Any) -> Any:
        """``value`` (JSON-like) with ``scrub`` applied to every string in it."""
        if isinstance(value, str):
            return self.scrub(value)
        if isinstance(value, dict):
            return {self.scrub(str(k)): self.scrub_all(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [self.scrub_all(v) for v in value]
        return value

    def _request(self, method: str, url: str, what: str, deadline: Deadline, stats: CallStats, *,
                 json_body: Any = None, files: Any = None, headers: dict[str, str] | None = None,
                 read_timeout: float | None = None, idempotent: bool = True) -> httpx.Response:
        if urlsplit(url).netloc != self._api_host:  # the token goes to the API's host only
            raise PredictionError(f"{what}: refusing to send the API token to {public_url(url)}")
        attempt = 0
        while True:
            left = deadline.check(what)
            if not idempotent:
                deadline.check_stop(what)  # no new paid request once the run is stopping
            stats.requests += 1
            timeout = self._timeout(left, read_timeout)
            budget = _limit(deadline, (timeout.read or 0) + self.settings.request_timeout_s, what)
            try:
                with _budget(budget):
                    response = self._http.request(method, url, json=json_body, files=files,
                                                  headers=self._headers(headers), timeout=timeout)
            except httpx.TransportError as exc:
                message = self.scrub(f"{type(exc).__name__}: {exc}")
                if not idempotent and not isinstance(exc, (httpx.ConnectError, httpx.ConnectTimeout,
                                                           httpx.PoolTimeout)):
                    # The request may have reached Replicate and created a (paid) prediction: do not repeat it.
                    raise CreationUncertain(f"{what}: {message}; the request may have reached Replicate, so it is "
                                            "not repeated") from None
                attempt = self._retry_or_fail(_Retry(None, None, message), attempt, what, deadline, stats)
                continue
            if response.status_code == 429 or response.status_code >= 500:
                retry = _Retry(response.status_code, _retry_after(response), self._message(response))
                attempt = self._retry_or_fail(retry, attempt, what, deadline, stats)
                continue
            if response.status_code >= 400:
                raise ReplicateError(f"{what}: HTTP {response.status_code}: {self._message(response)}",
                                     response.status_code)
            return response

    def _retry_or_fail(self, retry: "_Retry", attempt: int, what: str, deadline: Deadline, stats: CallStats) -> int:
        """Count the failure, wait (Retry-After or backoff) and return the next attempt number, or raise
        (StopRequested when the run is stopping: nothing is retried then)."""
        label = "network error" if retry.status is None else f"HTTP {retry.status}"
        deadline.check_stop(f"{what}: {label} ({retry.message})")
        if attempt >= self.settings.max_retries:
            raise ReplicateError(f"{what}: {label} after {attempt + 1} attempts: {retry.message}", retry.status)
        if retry.status == 429:
            stats.rate_limited += 1
        elif retry.status is None:
            stats.network_errors += 1
        else:
            stats.server_errors += 1
        pause = retry.after if retry.status == 429 and retry.after is not None else self._backoff(attempt)
        if pause > deadline.left():
            raise ReplicateError(f"{what}: {label} ({retry.message}); waiting {pause:.3g} s more would pass the "
                                 f"per-example timeout of {deadline.seconds:g} s", retry.status)
        log.warning("%s: %s (%s); retrying in %.2f s (%d of %d)", what, label, retry.message, pause, attempt + 1,
                    self.settings.max_retries)
        self._nap(pause, deadline)
        deadline.check_stop(f"{what}: {label} ({retry.message})")
        return attempt + 1

    def _backoff(self, attempt: int) -> float:
        """Exponential backoff with jitter: uniform in [d/2, d], d = min(max, base 2^attempt)."""
        d = min(self.settings.backoff_max_s, self.settings.backoff_base_s * 2.0 ** attempt)
        with self._rng_lock:
            return d * (0.5 + 0.5 * self._rng.random())

    def _pause(self, seconds: float, deadline: Deadline, what: str) -> None:
        left = deadline.check(what)
        self._nap(min(seconds, left), deadline)
        deadline.check(what)

    def _nap(self, seconds: float, deadline: Deadline) -> None:
        """Sleep ``seconds``; woken at once when the example's stop is set (the caller then checks it)."""
        if self._sleep is not None:
            self._sleep(seconds)
        elif deadline.stop is not None:
            deadline.stop.wait(seconds)
        else:
            time.sleep(seconds)

    def _message(self, response: httpx.Response) -> str:
        """The API's message from an error answer (problem JSON ``detail``/``title``, or the text), scrubbed."""
        try:
            if not response.is_stream_consumed:
                response.read()
            body = response.json()
        except (ValueError, httpx.HTTPError):
            body = None
        if isinstance(body, dict):
            text = body.get("detail") or body.get("error") or body.get("title") or json.dumps(body)[:300]
        else:
            try:
                text = response.text[:300].strip()
            except (httpx.HTTPError, ValueError):
                text = ""
        return self.scrub(str(text) or response.reason_phrase or "no message")

    def _json(self, response: httpx.Response, what: str) -> Any:
        try:
            return response.json()
        except ValueError:
            raise ReplicateError(f"{what}: Replicate's answer is not JSON (HTTP {response.status_code})") from None

    def _prediction(self, response: httpx.Response, what: str) -> dict[str, Any]:
        body = self._json(response, what)
        if not isinstance(body, dict) or not isinstance(body.get("id"), str) or not body["id"]:
            raise ReplicateError(f"{what}: Replicate's answer is not a prediction (no id)")
        return body


class CreationUncertain(PredictionError):
    """A creation request that may have reached Replicate without an answer (it is not repeated)."""


class _Retry(Exception):
    """A retriable failure: an HTTP status (None: a network error), its Retry-After and the message."""

    def __init__(self, status: int | None, after: float | None, message: str):
        super().__init__(message)
        self.status, self.after, self.message = status, after, message


def _retry_after(response: httpx.Response) -> float | None:
    """Seconds from a ``Retry-After`` header (seconds or an HTTP date); None when absent or unreadable."""
    value = response.headers.get("retry-after")
    if not value:
        return None
    try:
        return max(0.0, float(value))
    except ValueError:
        pass
    try:
        when = email.utils.parsedate_to_datetime(value)
    except (TypeError, ValueError):
        return None
    return max(0.0, when.timestamp() - time.time())


def _check_video(path: Path, what: str) -> None:
    """A PredictionError unless ``path`` decodes as a video with at least one frame."""
    try:
        check_decodable(path)
        if probe_video(path).n_frames == 0:
            raise PredictionError(f"{what}: the output has no video frames; refused")
    except VideoError as exc:
        raise PredictionError(f"{what}: the output is not a decodable video ({exc.reason}); refused") from None
