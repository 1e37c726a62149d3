"""Model selection by a rule fixed in advance, run inside the fold it serves (nested cross-validation).

`SelectedEstimator.fit(training textures)` runs K-fold cross-validation over those textures only
(repeated with `repeats` shuffles), scores every candidate by its out-of-fold MAE per attribute,
picks per attribute the candidate with the lowest one (ties: the earlier candidate), and refits
what the picks need on all its training textures. Run through `loocv`, every outer fold makes its
own pick without seeing the held-out texture, so the LOOCV number of the selected model carries no
selection bias. `hapticlink train` runs the very same fit on every rated texture to make the served
model. The rule and the candidate list are written down in docs/models.md.

Candidates are base estimators (fit in each inner fold) and means of bases (ensembles), whose
out-of-fold predictions are the mean of their members' — scored at no extra cost.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from models.offline.evaluation.data import TextureData
from models.offline.evaluation.estimators import Estimator, common_views, require_targets, union_modality, window_mean
from texture_library.attributes import ATTRIBUTES, RATING_MAX, RATING_MIN, REPORT_SCALE


class SelectedEstimator(Estimator):
    """Per attribute, the candidate with the lowest inner-CV MAE.

    bases: name → zero-argument factory of a fresh estimator (the registry supplies them);
    means: name → names of bases whose predictions it averages; candidates are bases then means,
    in the order given (the order breaks ties); folds: inner K; repeats: the inner K-fold repeated
    with this many shuffles (seeded by the fit's seed)."""

    def __init__(
        self,
        bases: dict[str, Callable[[], Estimator]],
        means: dict[str, tuple[str, ...]] | None = None,
        folds: int = 5,
        repeats: int = 2,
        name: str = "selected",
    ):
        means = dict(means or {})
        if not bases:
            raise ValueError("selection needs at least one base candidate")
        for m, members in means.items():
            unknown = [b for b in members if b not in bases]
            if len(members) < 2 or unknown:
                raise ValueError(f"mean candidate {m!r} needs ≥ 2 members among the bases, got {members}")
        if set(bases) & set(means):
            raise ValueError(f"candidate names must be unique, both bases and means: {sorted(set(bases) & set(means))}")
        if folds < 2:
            raise ValueError(f"inner folds must be ≥ 2, got {folds}")
        if repeats < 1:
            raise ValueError(f"repeats must be ≥ 1, got {repeats}")
        self.factories = dict(bases)
        self.means = {m: tuple(v) for m, v in means.items()}
        self.folds = folds
        self.repeats = repeats
        self.name = name
        self.modality = union_modality(f().modality for f in self.factories.values())  # what it may read

    @property
    def candidates(self) -> list[str]:
        return [*self.factories, *self.means]

    def members_of(self, candidate: str) -> tuple[str, ...]:
        return self.means.get(candidate, (candidate,))

    def inner_errors(self, data: TextureData, seed: int) -> np.ndarray:
        """(candidates, 4) out-of-fold MAE on the 0–100 scale over the training textures `data`."""
        from sklearn.model_selection import KFold

        y = require_targets(data)
        if len(y) < self.folds:
            raise ValueError(
                f"inner {self.folds}-fold selection needs at least {self.folds} training textures, got {len(y)}"
            )
        bases = list(self.factories)
        err = np.zeros((len(self.candidates), 4))
        for r in range(self.repeats):
            oof = np.zeros((len(bases), len(y), 4))
            for tr, va in KFold(self.folds, shuffle=True, random_state=seed * 1009 + r).split(y):
                train, held = data.take(tr), data.take(va).with_targets(None)
                for b, name in enumerate(bases):
                    oof[b, va] = self.factories[name]().fit(train, seed).predict(held)
            preds = [
                oof[bases.index(c)]
                if c in self.factories
                else oof[[bases.index(b) for b in self.means[c]]].mean(axis=0)
                for c in self.candidates
            ]
            err += np.stack([np.abs(np.clip(p, RATING_MIN, RATING_MAX) - y).sum(axis=0) for p in preds])
        return err / (self.repeats * len(y)) * REPORT_SCALE

    def fit(self, data: TextureData, seed: int) -> SelectedEstimator:
        names = self.candidates
        self.inner_mae = self.inner_errors(data, seed)
        self.chosen = [names[int(np.argmin(self.inner_mae[:, j]))] for j in range(4)]  # argmin: the first of ties
        needed = [b for b in self.factories if any(b in self.members_of(c) for c in self.chosen)]
        self.models = {b: self.factories[b]().fit(data, seed) for b in needed}
        self.modality = union_modality(m.modality for m in self.models.values())
        return self

    def predict_windows(self, data: TextureData) -> list[np.ndarray]:
        """Per texture, (n_i, 4) answers of the exported graph to its windows, before the output clip."""
        base = {b: m.predict_windows(data) for b, m in self.models.items()}
        out = []
        for i in range(len(data)):
            cols = [np.mean([base[b][i][:, j] for b in self.members_of(c)], axis=0) for j, c in enumerate(self.chosen)]
            out.append(np.stack(cols, axis=1))
        return out

    def predict(self, data: TextureData) -> np.ndarray:
        return window_mean(self.predict_windows(data))

    def n_params(self) -> int:
        return int(sum(m.n_params() for m in self.models.values()))

    def fit_info(self) -> dict:
        return {
            "chosen": dict(zip(ATTRIBUTES, self.chosen)),
            "inner_mae": {n: dict(zip(ATTRIBUTES, map(float, row))) for n, row in zip(self.candidates, self.inner_mae)},
            "members": {b: m.fit_info() for b, m in self.models.items()},
        }

    @property
    def views(self) -> int | None:
        return common_views(self.models.values())

    def pooled_views(self, stored: int) -> int:
        return next(iter(self.factories.values()))().pooled_views(stored)

    def add_graph(self, g) -> str:
        base = {b: m.add_graph(g) for b, m in self.models.items()}
        distinct = list(dict.fromkeys(self.chosen))
        outputs = [g.mean_of([base[b] for b in self.members_of(c)]) for c in distinct]
        return g.pick_columns(outputs, [distinct.index(c) for c in self.chosen])

    def export(self, path, metadata: dict[str, str]):
        from models.offline.onnx_graph import export_graph

        return export_graph(self, path, metadata)
