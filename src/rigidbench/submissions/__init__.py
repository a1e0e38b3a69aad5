"""Submissions: a run's results, per-example records and the submitter's card as one checked bundle.

- ``bundle``: the bundle's layout and SHA-256 manifest; ``load_submission(path) -> Submission`` reads an
  archive or an extracted folder back, checking the manifest (``SubmissionError`` names a changed, missing or
  unlisted file);
- ``card``: the card's schema, as data (``CARD_FIELDS``), and its check;
- ``provenance``: what the run knows, filled from its results.json, run.json and predictions, never typed;
- ``validate``: why a run cannot be submitted, one line per problem;
- ``verify``: recomputing every aggregate of results.json from the per-example records.

``rigidbench submit`` and ``rigidbench verify`` (``commands.submitting``) drive them; ``docs/submitting.md``
describes the path from a run to a bundle.
"""

from .bundle import Submission, SubmissionError, load_submission

__all__ = ["Submission", "SubmissionError", "load_submission"]
