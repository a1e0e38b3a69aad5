"""The submission card: what only the submitter knows about how the videos were made and scored.

The schema is data: ``CARD_FIELDS``, one ``CardField`` per field (its dotted path in the YAML, its type, whether it
is required, and when it is required only under a condition, that condition), and ``ONE_OF`` (groups of which at
least one field must be given). ``card_problems(card)`` checks a card against them and returns one line per
problem (a field missing, of the wrong type, out of range, or unknown); ``docs/card.example.yaml`` is a complete
card, and ``docs/submitting.md`` lists the fields.

What the run itself knows (the dataset, protocol, perception, versions, seeds, record digests) is never part of
the card: ``submit`` fills it in under ``provenance:`` (``submissions.provenance``).
"""

from __future__ import annotations

import difflib
import re
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

#: type name -> what a value of it must be (the words of a problem line)
TYPES = {
    "text": "a non-empty text",
    "int": "a whole number",
    "number": "a number",
    "bool": "true or false",
    "choice": "one of",
    "url": "an http(s) URL",
    "email": "an e-mail address",
    "resolution": "WIDTHxHEIGHT in pixels, e.g. 1280x720",
    "digest": "sha256:<64 hex digits>",
    "currency": "a three-letter currency code, e.g. USD",
}


@dataclass(frozen=True)
class CardField:
    """One card field: ``path`` (dotted: ``generation.fps`` is ``fps`` under ``generation:``), ``type`` (a key of
    ``TYPES``), ``required``; ``unless``: (another field's path, a value) under which it is not required (e.g. the
    prompt template unless ``generation.prompt_rewriting`` is false); ``choices`` of a "choice"; ``minimum``
    (at least) and ``above`` (more than) of a number or whole number; ``help``: what it holds."""

    path: str
    type: str
    required: bool
    help: str
    unless: tuple[str, Any] | None = None
    choices: tuple[str, ...] = ()
    minimum: float | None = None
    above: float | None = None


CARD_FIELDS: tuple[CardField, ...] = (
    CardField("name", "text", False, "the entry's display name (default: model.name)"),
    CardField("model.name", "text", True, "the video model, e.g. Wan2.2-I2V-A14B"),
    CardField("model.version", "text", False, "its release or version (this or model.checkpoint_digest)"),
    CardField("model.checkpoint_digest", "digest", False, "SHA-256 of the checkpoint file used (this or "
                                                          "model.version)"),
    CardField("access.kind", "choice", True, "how the model was run", choices=("open-weights", "api")),
    CardField("access.provider", "text", True, "who serves the model or its weights (e.g. Hugging Face, an API "
                                               "vendor)"),
    CardField("generation.resolution", "resolution", True, "the resolution the model generated at"),
    CardField("generation.fps", "number", True, "frames per second of the generated clips", above=0),
    CardField("generation.frames", "int", True, "frames per generated clip", minimum=1),
    CardField("generation.samples_per_example", "int", True, "clips generated per example", minimum=1),
    CardField("generation.best_of_n", "int", True, "N of best-of-N (1: the only clip was scored)", minimum=1),
    CardField("generation.selection", "text", True, "how the scored clip was chosen among the N",
              unless=("generation.best_of_n", 1)),
    CardField("generation.prompt_rewriting", "bool", True, "whether prompts were rewritten (upsampled) before "
                                                           "generation"),
    CardField("generation.prompt_template", "text", True, "the rewriting instruction or template",
              unless=("generation.prompt_rewriting", False)),
    CardField("people.generated_by", "text", True, "who generated the videos"),
    CardField("people.scored_by", "text", True, "who ran rigidbench evaluate"),
    CardField("compute.gpu_type", "text", True, "GPU model used for generation", unless=("access.kind", "api")),
    CardField("compute.gpu_count", "int", True, "GPUs used at once", unless=("access.kind", "api"), minimum=1),
    CardField("compute.gpu_hours", "number", True, "GPU hours spent generating", unless=("access.kind", "api"),
              minimum=0),
    CardField("cost.amount", "number", True, "what generating the videos cost", minimum=0),
    CardField("cost.currency", "currency", True, "the currency of cost.amount"),
    CardField("licence.model", "text", True, "the model's or API's licence"),
    CardField("licence.terms", "url", True, "the terms of use that apply to the generated videos"),
    CardField("contact", "email", True, "who to ask about this entry"),
    CardField("report_url", "url", False, "a paper, report or model card describing the entry"),
)

#: groups of fields of which at least one must be given
ONE_OF: tuple[tuple[str, ...], ...] = (("model.version", "model.checkpoint_digest"),)

_EMAIL = re.compile(r"^[^@\s]+@[^@\s]+\.[^@\s]+$")
_DIGEST = re.compile(r"^sha256:[0-9a-f]{64}$")
_RESOLUTION = re.compile(r"^([1-9][0-9]*)x([1-9][0-9]*)$")
_CURRENCY = re.compile(r"^[A-Z]{3}$")

_MISSING = object()


def get_path(doc: dict, path: str) -> Any:
    """The value at the dotted ``path`` of nested mappings (``_MISSING`` when absent or null)."""
    value: Any = doc
    for key in path.split("."):
        if not isinstance(value, dict) or value.get(key) is None:
            return _MISSING
        value = value[key]
    return value


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def type_problem(f: CardField, value: Any) -> str | None:
    """Why ``value`` is not a valid ``f`` (None: it is)."""
    t = f.type
    ok = {"text": isinstance(value, str) and bool(value.strip()),
          "int": isinstance(value, int) and not isinstance(value, bool),
          "number": _is_number(value) and value == value and value not in (float("inf"), float("-inf")),
          "bool": isinstance(value, bool),
          "choice": value in f.choices,
          "url": isinstance(value, str) and urlsplit(value).scheme in ("http", "https")
          and bool(urlsplit(value).hostname),
          "email": isinstance(value, str) and bool(_EMAIL.match(value)),
          "resolution": isinstance(value, str) and bool(_RESOLUTION.match(value)),
          "digest": isinstance(value, str) and bool(_DIGEST.match(value)),
          "currency": isinstance(value, str) and bool(_CURRENCY.match(value))}[t]
    want = TYPES[t] + (" " + ", ".join(f.choices) if t == "choice" else "")
    if not ok:
        return f"expected {want}, got {value!r}"
    if f.minimum is not None and value < f.minimum:
        return f"must be >= {f.minimum:g}, got {value!r}"
    if f.above is not None and value <= f.above:
        return f"must be > {f.above:g}, got {value!r}"
    return None


def required(f: CardField, card: dict) -> bool:
    """Whether ``f`` must be given in ``card`` (its ``unless`` condition considered)."""
    if not f.required:
        return False
    return f.unless is None or get_path(card, f.unless[0]) != f.unless[1]


def _leaves(doc: dict, prefix: str = ""):
    for key, value in doc.items():
        path = f"{prefix}{key}"
        if isinstance(value, dict) and any(f.path.startswith(path + ".") for f in CARD_FIELDS):
            yield from _leaves(value, path + ".")
        else:
            yield path


def card_problems(card: dict, where: str = "card") -> list[str]:
    """One line per problem of ``card`` (a mapping read from YAML): a required field missing, a value of the wrong
    type or out of range, a field the schema does not know (with the nearest known name), none of a ``ONE_OF``
    group, or a ``provenance`` the submitter typed. Empty: the card is complete."""
    problems = []
    if "provenance" in card:
        problems.append(f"{where}: field 'provenance': filled from the run by `rigidbench submit`, never typed; "
                        "remove it from the card")
    known = {f.path for f in CARD_FIELDS}
    for path in _leaves({k: v for k, v in card.items() if k != "provenance"}):
        if path not in known:
            sections = {f.path.rsplit(".", 1)[0] for f in CARD_FIELDS if "." in f.path}
            close = difflib.get_close_matches(path, sorted(known | sections), n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            problems.append(f"{where}: field '{path}': not a card field{hint}; docs/card.example.yaml lists them")
    for f in CARD_FIELDS:
        value = get_path(card, f.path)
        if value is _MISSING:
            if required(f, card):
                problems.append(f"{where}: field '{f.path}': missing ({f.help})")
            continue
        why = type_problem(f, value)
        if why:
            problems.append(f"{where}: field '{f.path}': {why}")
    for group in ONE_OF:
        if all(get_path(card, p) is _MISSING for p in group):
            problems.append(f"{where}: field '{group[0]}': missing; give {' or '.join(group)}")
    n, samples = get_path(card, "generation.best_of_n"), get_path(card, "generation.samples_per_example")
    if isinstance(n, int) and isinstance(samples, int) and not isinstance(n, bool) and n > samples >= 1:
        problems.append(f"{where}: field 'generation.best_of_n': {n} is more than generation.samples_per_example "
                        f"({samples}); the best of N needs N samples")
    return problems
