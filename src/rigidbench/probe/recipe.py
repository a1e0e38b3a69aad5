"""How probing conditions Wan and fits INLP: each choice a recorded option, and the named recipes that
set them together (docs/probing.md, "Recipes"; docs/reproducing.md uses ``release``).

``Conditioning`` (extraction and intervention; recorded in the store's manifest and intervene.json,
and part of every clip's stage key):

* ``prompt``: ``task+suffix`` (ours: the evaluation prompt, the task prompt with the paper's suffix) or
  ``task`` (the release: the task prompt alone), read from the preprocessing cache, which holds both;
* ``padding``: ``zeros`` (ours: the text context after the prompt's tokens is zero, as the Wan pipeline
  pads it) or ``encoder`` (the release: UMT5's outputs at all 512 positions, as its cache stored them);
* ``clean_slot_timestep``: ``zero`` (ours: the clean slot 0's tokens see timestep 0) or ``noisy`` (the
  release: every token, slot 0 included, sees the one timestep t);
* ``dtype``: the transformer's forward precision, ``float32`` (ours) or ``bfloat16`` (the release);
* ``objective_dtype``: ``float32`` (ours) or ``bfloat16`` (the release: t rounded to bfloat16, which is
  the timestep the model sees, sigma of the schedule timestep nearest it, noised latent and target in
  bfloat16; the paper's tau 0.1 .. 0.9 then use schedule indices 93, 303, 502, 698, 899);
* ``noise``: ``per-clip`` (ours: a draw seeded by a hash of the seed and the clip id) or ``shared`` (the
  release: one tensor, the same for every clip, from a generator seeded with the seed).

Recipes: ``ours`` (the defaults above, INLP ``stable``) and ``release`` (every release choice above, INLP
``release``: ``inlp.inlp_release``). A command-line option given beside ``--recipe`` overrides that one
choice, and the outputs record the result.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace

from ..errors import UserError

CHOICES = {
    "prompt": ("task+suffix", "task"),
    "padding": ("zeros", "encoder"),
    "clean_slot_timestep": ("zero", "noisy"),
    "dtype": ("float32", "bfloat16"),
    "objective_dtype": ("float32", "bfloat16"),
    "noise": ("per-clip", "shared"),
}
INLP_PROCEDURES = ("stable", "release")
RECIPE_NAMES = ("ours", "release")
DEFAULT_RECIPE = "ours"


@dataclass(frozen=True)
class Conditioning:
    """What the transformer is given at extraction and intervention (module docstring); the first choice of
    each is ours, the second the release's."""

    prompt: str = "task+suffix"
    padding: str = "zeros"
    clean_slot_timestep: str = "zero"
    dtype: str = "float32"
    objective_dtype: str = "float32"
    noise: str = "per-clip"

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            if value not in CHOICES[f.name]:
                raise UserError(f"probe conditioning: {f.name} must be one of {', '.join(CHOICES[f.name])}, "
                                f"got {value!r}")

    def as_dict(self) -> dict:
        return asdict(self)

    def key_part(self) -> dict | None:
        """What a stage key adds for this conditioning: nothing for ours, so stores and outputs made before
        these options existed (all with ours) keep their keys; the whole record otherwise."""
        return None if self == Conditioning() else self.as_dict()

    @classmethod
    def from_record(cls, record: dict | None) -> Conditioning:
        """From a manifest's ``conditioning`` record (absent: a store made with ours)."""
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in (record or {}).items() if k in known})


RELEASE_CONDITIONING = Conditioning(prompt="task", padding="encoder", clean_slot_timestep="noisy", dtype="bfloat16",
                                    objective_dtype="bfloat16", noise="shared")


@dataclass(frozen=True)
class Recipe:
    name: str
    conditioning: Conditioning
    inlp: str  # INLP procedure: stable | release


RECIPES = {"ours": Recipe("ours", Conditioning(), "stable"),
           "release": Recipe("release", RELEASE_CONDITIONING, "release")}


def recipe(name: str | None) -> Recipe:
    """The recipe ``name`` (None: ours); UserError naming the known ones."""
    found = RECIPES.get(DEFAULT_RECIPE if name is None else name)
    if found is None:
        raise UserError(f"unknown probe recipe {name!r}; use one of {', '.join(RECIPE_NAMES)}")
    return found


def conditioning_with(base: Conditioning, **overrides) -> Conditioning:
    """``base`` with the given choices replaced (None values are ignored)."""
    given = {k: v for k, v in overrides.items() if v is not None}
    return replace(base, **given) if given else base


def recipe_label(name: str, conditioning: Conditioning, inlp: str | None = None) -> str:
    """``name`` when the choices equal that recipe's, else ``name+changes`` (what the outputs record)."""
    base = recipe(name)
    same = conditioning == base.conditioning and (inlp is None or inlp == base.inlp)
    return base.name if same else f"{base.name}+changes"
