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


def pooled_bases(views: int | None = None) -> dict:
    """The base candidates of `selected`, fixed in advance (docs/models.md): name → factory.

    Each reads every stored image view pooled (views=None) or the first `views`, and weighs touch
    per attribute inside its own fit; every one exports to ONNX."""
    return {
        "ridge-pooled": lambda: KernelRidgeEstimator("both", "linear", views),
        "krr-pooled": lambda: KernelRidgeEstimator("both", "rbf", views),
        "ksvr-pooled": lambda: KernelSVREstimator("both", "rbf", views),
    }


def _mean_pooled(views: int | None = None) -> MeanOfEstimator:
    bases = pooled_bases(views)
    return MeanOfEstimator({b: bases[b] for b in POOLED_MEANS["mean-pooled"]}, name="mean-pooled")


def _base(name: str):
    return lambda views=None: pooled_bases(views)[name]()


CLASSICAL.update(
    {
        **{name: _base(name) for name in POOLED_BASES},
        "mean-pooled": _mean_pooled,
        "selected": lambda views=None, **kw: SelectedEstimator(pooled_bases(views), POOLED_MEANS, **kw),
    }
)
SHUFFLED_PREFIX = "shuffled-"
ENSEMBLE_SUFFIX = "-ensemble"


@dataclass(frozen=True)
class EstimatorSpec:
    """A picklable recipe for an estimator: registry name plus keyword options."""

    name: str
    options: dict = field(default_factory=dict)

    def build(self) -> Estimator:
        return build_estimator(self.name, **self.options)


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
