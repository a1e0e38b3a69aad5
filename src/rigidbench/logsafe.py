"""Log lines never carry a URL's query, its user information or a known secret.

httpx logs every request's full URL at INFO (``HTTP Request: GET https://host/path?token=... "200 OK"``)
and httpcore's DEBUG trace prints raw response headers (a redirect's ``Location``, cookies).
``configure_logging`` (the command line and each worker process call it) therefore:

- quiets the HTTP libraries' loggers (``QUIET_LOGGERS``) to WARNING; with ``-v`` httpx's request
  lines come back (scrubbed), httpcore's header trace never does;
- scrubs every log record the process makes, from any logger at any level, as it is made (before
  any handler sees it): each URL in the message, in a logged exception's traceback and in a stack
  becomes ``public_url`` (scheme, host, port and path; no user information, query or fragment;
  credential-looking path segments ``[REDACTED]``), and each remembered secret
  (``remember_secret``: the API token of each hosted-model client made) becomes ``[REDACTED]``.

``ScrubFilter`` does the same as a ``logging.Filter``, for a library module to attach to the loggers
it drives (``install_filter``), so that a program that configures logging itself is covered too.

Standard library only.
"""

from __future__ import annotations

import logging
import re
from typing import Callable, Iterable
from urllib.parse import unquote, urlsplit, urlunsplit

REDACTED = "[REDACTED]"
#: Loggers of libraries that print request URLs or headers: WARNING unless -v (httpx), or always (httpcore).
QUIET_LOGGERS = ("httpx", "httpcore", "urllib3", "huggingface_hub")
#: Of those, the ones whose INFO/DEBUG lines -v shows (scrubbed): httpx's one line per request.
VERBOSE_LOGGERS = ("httpx",)
LOG_FORMAT = "%(levelname)s %(name)s: %(message)s"

#: a path segment that looks like a credential: a name such as token, key or signature with a value, a
#: Replicate API token (r8_...), a JSON web token, or path parameters (;jsessionid=...)
_CREDENTIAL = re.compile(r"(?i)(token|key|secret|sig|signature|auth|password|passwd|credential|session|bearer)"
                         r"[^/]*[=:]|\br8_[A-Za-z0-9]{8,}|\beyJ[A-Za-z0-9_-]{8,}\.|;")
_URL = re.compile(r"[A-Za-z][A-Za-z0-9+.-]*://[^\s\"'<>]+")
_SECRETS: set[str] = set()


def public_url(url: str) -> str:
    """``url`` without user information, query or fragment, and with every credential-looking path segment
    replaced by [REDACTED] (safe to log and record)."""
    try:
        parts = urlsplit(str(url))
        host = parts.hostname or ""
        if parts.port:
            host = f"{host}:{parts.port}"
    except ValueError:
        return REDACTED
    segments = [REDACTED if _CREDENTIAL.search(unquote(seg)) else seg for seg in parts.path.split("/")]
    return urlunsplit((parts.scheme, host, "/".join(segments), "", ""))


def scrub_text(text: str, secrets: Iterable[str] = ()) -> str:
    """``text`` with every URL in it made public (``public_url``) and every secret (those given and those
    remembered) replaced by [REDACTED]."""
    text = _URL.sub(lambda m: public_url(m.group(0)), str(text))
    for secret in (*secrets, *_SECRETS):
        if secret:
            text = text.replace(secret, REDACTED)
    return text


def remember_secret(secret: str) -> None:
    """Keep ``secret`` (an API token) out of every log record from now on."""
    if secret:
        _SECRETS.add(secret)


_TRACEBACKS = logging.Formatter()


def scrub_record(record: logging.LogRecord) -> logging.LogRecord:
    """``record`` with its message, exception text and stack scrubbed in place (``scrub_text``)."""
    try:
        message = record.getMessage()
    except Exception:  # noqa: BLE001 - a malformed record is reported by logging itself when emitted
        return record
    clean = scrub_text(message)
    if clean != message:
        record.msg, record.args = clean, ()
    if record.exc_info and not record.exc_text:
        record.exc_text = scrub_text(_TRACEBACKS.formatException(record.exc_info))
    if record.stack_info:
        record.stack_info = scrub_text(record.stack_info)
    return record


class ScrubFilter(logging.Filter):
    """Scrubs each record of the logger it is attached to (``scrub_record``); never drops one."""

    def filter(self, record: logging.LogRecord) -> bool:
        scrub_record(record)
        return True


_FILTER = ScrubFilter()


def install_filter(names: Iterable[str]) -> None:
    """Attach the scrubbing filter to the loggers ``names`` (records logged on them directly; idempotent)."""
    for name in names:
        logger = logging.getLogger(name)
        if _FILTER not in logger.filters:
            logger.addFilter(_FILTER)


_scrubbing_factory: Callable[..., logging.LogRecord] | None = None


def _scrub_every_record() -> None:
    """Make the process's record factory scrub each record as it is made (idempotent)."""
    global _scrubbing_factory
    if logging.getLogRecordFactory() is _scrubbing_factory:
        return
    make = logging.getLogRecordFactory()

    def factory(*args, **kwargs) -> logging.LogRecord:
        return scrub_record(make(*args, **kwargs))

    _scrubbing_factory = factory
    logging.setLogRecordFactory(factory)


def configure_logging(level: int = logging.INFO, fmt: str = LOG_FORMAT) -> None:
    """The process's logging: root at ``level`` on stderr (when nothing configured it yet), the HTTP libraries
    quiet (``QUIET_LOGGERS``; at DEBUG, httpx's request lines stay), and every record scrubbed as it is made."""
    logging.basicConfig(level=level, format=fmt)
    _scrub_every_record()
    for name in QUIET_LOGGERS:
        verbose = level <= logging.DEBUG and name in VERBOSE_LOGGERS
        logging.getLogger(name).setLevel(logging.NOTSET if verbose else logging.WARNING)
