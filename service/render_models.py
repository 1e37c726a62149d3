"""The library's rendering models as served: each entry's RenderModel, encoded once at start-up.

`GET /library/{id}/model` answers from here (JSON, or the compact LSF-quantised payload of
`texture_library.model_codec`), and window events name `chosen_model_version` from here. Built with the
runtime, so a library holding a model over `MAX_RENDER_MODEL_BYTES` is refused at start-up (/ready says
which entry) and nothing larger is ever served.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

from texture_library import model_codec
from texture_library.library import Library
from texture_library.render_model import RenderModel, library_digest


@dataclass(frozen=True)
class ServedRenderModel:
    """One entry's model: the document, its JSON body, its compact body; taps_from: for a learnt model, the library
    entry whose recorded taps it carries (a delta base an operator holding the library already has), else None."""

    model: RenderModel
    json_body: bytes
    compact_body: bytes
    taps_from: str | None = None

    @property
    def version(self) -> str:
        return self.model.model_version

    @cached_property
    def body(self) -> bytes:
        """The compact payload's inflated body: what a delta is made against (model_codec.encode_delta)."""
        return model_codec.body(self.compact_body)


@dataclass(frozen=True)
class RenderCatalog:
    """Every entry's served model, by library id."""

    models: dict[str, ServedRenderModel]

    @classmethod
    def from_library(cls, library: Library) -> RenderCatalog:
        """ValueError naming the entry when a model is unreadable or over the served size bound."""
        out = {}
        for entry_id in library.ids:
            try:
                doc = RenderModel.from_vibration_model(entry_id, library.model(entry_id))
            except (ValueError, OSError) as exc:
                raise ValueError(f"library {library.name!r}, entry {entry_id!r}: {exc}") from None
            out[entry_id] = ServedRenderModel(doc, doc.to_json_bytes(), model_codec.encode(doc))
        return cls(out)

    @cached_property
    def digest(self) -> str:
        """The library's digest (texture_library.render_model.library_digest): an operator that names it holds
        every entry."""
        return library_digest({i: m.version for i, m in self.models.items()})

    def version(self, entry_id: str) -> str | None:
        served = self.models.get(entry_id)
        return None if served is None else served.version
