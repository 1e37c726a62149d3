"""Estimators by name, so folds in other processes (or on a Ray cluster) can rebuild them."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial

from models.offline.evaluation.estimators import (
    Estimator,
    KNNEstimator,
    MeanEstimator,
    RidgeEstimator,
    ShuffledLabels,
    StackedEstimator,
    SVREstimator,
    WindowSVREstimator,
)
from models.offline.evaluation.kernel import KernelRidgeEstimator, KernelSVREstimator, MeanOfEstimator
from models.offline.evaluation.selection import SelectedEstimator

CLASSICAL = {
    "mean": lambda **kw: MeanEstimator(),
    "stack-both": lambda **kw: StackedEstimator(
        {
            "svr-visual": lambda: SVREstimator("visual"),
            "ridge-both": lambda: RidgeEstimator("both"),
            "knn-visual": lambda: KNNEstimator("visual"),
        },
        **kw,
    ),
    "svr-tactile-windows": lambda **kw: WindowSVREstimator(**kw),
    **{f"ridge-{m}": partial(RidgeEstimator, m) for m in ("tactile", "visual", "both")},
    **{f"knn-{m}": partial(KNNEstimator, m) for m in ("tactile", "visual", "both")},
    **{f"svr-{m}": partial(SVREstimator, m) for m in ("tactile", "visual", "both")},
    **{f"svr-{m}-views": partial(SVREstimator, m, views="all") for m in ("visual", "both")},
}


POOLED_BASES = ("ridge-pooled", "krr-pooled", "ksvr-pooled")
POOLED_MEANS = {"mean-pooled": POOLED_BASES}


def pooled_bases(views: int | None = None, modality: str = "both", loo: str = "centred") -> dict:
    """The base candidates of `selected`, fixed in advance (docs/models.md): name → factory.

    Each reads every stored image view pooled (views=None) or the first `views`, and weighs touch
    per attribute inside its own fit; every one exports to ONNX. modality "visual": the same models
    on the image alone (an image-only dataset). loo: the kernel ridges' leave-one-out criterion ("centred", the
    rule's; "exact": `selected-exact-loo`, reported beside it)."""
    return {
        "ridge-pooled": lambda: KernelRidgeEstimator(modality, "linear", views, loo=loo),
        "krr-pooled": lambda: KernelRidgeEstimator(modality, "rbf", views, loo=loo),
        "ksvr-pooled": lambda: KernelSVREstimator(modality, "rbf", views),
    }


def _mean_pooled(views: int | None = None, modality: str = "both") -> MeanOfEstimator:
    bases = pooled_bases(views, modality)
    return MeanOfEstimator({b: bases[b] for b in POOLED_MEANS["mean-pooled"]}, name="mean-pooled")


def _base(name: str):
    return lambda views=None, modality="both": pooled_bases(views, modality)[name]()


# The candidates of `selected-image`, fixed before any leave-one-out number on hassan2023 was computed
# (docs/models.md): kernel ridge, linear and RBF, on each set of visual feature groups. Which groups an
# attribute reads is chosen inside the folds, with the kernel, by the nested rule of `selected`.
IMAGE_BLOCK_SETS: dict[str, tuple[str, ...]] = {
    "backbone": ("backbone",),
    "classic": ("glcm", "lbp", "spectrum", "colour", "grids", "scattering"),
    "all": ("backbone", "glcm", "lbp", "spectrum", "colour", "grids", "scattering"),
    "glcm": ("glcm",),
    "lbp": ("lbp",),
    "spectrum": ("spectrum",),
    "colour": ("colour",),
    "grids": ("grids",),
    "scattering": ("scattering",),
}


def image_bases(views: int | None = None) -> dict:
    """name → factory of every `selected-image` candidate: {ridge, krr} × IMAGE_BLOCK_SETS, image only."""
    return {
        f"{family}-{set_name}": (
            lambda kernel=kernel, blocks=blocks: KernelRidgeEstimator("visual", kernel, views, visual_blocks=blocks)
        )
        for set_name, blocks in IMAGE_BLOCK_SETS.items()
        for family, kernel in (("ridge", "linear"), ("krr", "rbf"))
    }


def _image_base(name: str):
    return lambda views=None: image_bases(views)[name]()


CLASSICAL.update(
    {
        **{name: _base(name) for name in POOLED_BASES},
        "mean-pooled": _mean_pooled,
        "selected": lambda views=None, modality="both", **kw: SelectedEstimator(
            pooled_bases(views, modality), POOLED_MEANS, **kw
        ),
        # the same rule with the kernel ridges' exact leave-one-out criterion: a sensitivity row, not a candidate
        "selected-exact-loo": lambda views=None, modality="both", **kw: SelectedEstimator(
            pooled_bases(views, modality, loo="exact"), POOLED_MEANS, name="selected-exact-loo", **kw
        ),
        "selected-image": lambda views=None, **kw: SelectedEstimator(image_bases(views), name="selected-image", **kw),
        **{f"{name}-image": _image_base(name) for name in image_bases()},
    }
)
# Models that weigh touch inside their fit (a weight of 0 included): on an image-only dataset they run
# as their image-only variant; every other model that reads touch is refused there.
TOUCH_OPTIONAL = (*POOLED_BASES, "mean-pooled", "selected")
SHUFFLED_PREFIX = "shuffled-"
ENSEMBLE_SUFFIX = "-ensemble"


@dataclass(frozen=True)
class EstimatorSpec:
    """A picklable recipe for an estimator: registry name plus keyword options."""

    name: str
    options: dict = field(default_factory=dict)

    def build(self) -> Estimator:
        return build_estimator(self.name, **self.options)


def for_dataset(spec: EstimatorSpec, image_only: bool, dataset: str = "the dataset") -> EstimatorSpec:
    """The spec to run on a dataset: as is when it has recordings; on an image-only dataset a model that weighs
    touch optionally becomes its image-only variant, an image model stays, and a model that needs touch is
    refused with a ValueError naming the model and the missing modality."""
    if not image_only:
        return spec
    base = spec.name[len(SHUFFLED_PREFIX) :] if spec.name.startswith(SHUFFLED_PREFIX) else spec.name
    if base in TOUCH_OPTIONAL:
        return EstimatorSpec(spec.name, {**spec.options, "modality": "visual"})
    modality = spec.build().modality
    if modality in ("tactile", "both"):
        raise ValueError(
            f"model {spec.name!r} needs touch (tactile recordings; it reads {modality}), but {dataset} is "
            "image-only: it has no recordings. Image models run on it: mean, ridge-visual, knn-visual, svr-visual, "
            f"{', '.join(TOUCH_OPTIONAL)} (as image-only variants), selected-image, *-image"
        )
    return spec


def names() -> list[str]:
    from models.offline.nets.presets import NAMES as NET_NAMES

    return sorted(CLASSICAL) + list(NET_NAMES) + [n + ENSEMBLE_SUFFIX for n in NET_NAMES]


def build_estimator(name: str, **options) -> Estimator:
    """`shuffled-<name>` wraps <name> in the shuffled-label control; `<net>-ensemble` averages 3 seeds of a network."""
    if name.startswith(SHUFFLED_PREFIX):
        return ShuffledLabels(build_estimator(name[len(SHUFFLED_PREFIX) :], **options))
    if name in CLASSICAL:
        try:
            return CLASSICAL[name](**options)
        except TypeError as exc:  # e.g. --max-epochs given to ridge
            raise ValueError(f"model {name!r} does not take {', '.join(sorted(options))}: {exc}") from None
    from models.offline.nets.presets import NAMES as NET_NAMES

    try:
        if name in NET_NAMES:
            from models.offline.evaluation.net_estimator import NetEstimator

            return NetEstimator(name, **options)
        if name.endswith(ENSEMBLE_SUFFIX) and name[: -len(ENSEMBLE_SUFFIX)] in NET_NAMES:
            from models.offline.evaluation.net_estimator import NetEnsemble

            return NetEnsemble(name[: -len(ENSEMBLE_SUFFIX)], **options)
    except TypeError as exc:  # e.g. --views given to a network
        raise ValueError(f"model {name!r} does not take {', '.join(sorted(options))}: {exc}") from None
    raise ValueError(f"unknown model {name!r}; known: {', '.join(names())}")
