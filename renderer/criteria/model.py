"""The learned criterion: a model bundle in this process, or a verdict server, behind one
adapter per kind of scorer."""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from learning.stoprule import CONVERGED, NOISY, StopRule, hold_dotted
from noisefeat.runtime import torch_threads

from .batch import UnitBatch
from .contract import Criterion, Tally
from .registry import BLOCK, Setting, declare

if TYPE_CHECKING:
    import torch

    from ..spec import RenderSpec


class ScoresBlocks(Protocol):
    """Anything that turns linear RGB blocks into verdicts (local Model or RemoteModel)."""

    def score_blocks(self, blocks: np.ndarray, quick: np.ndarray | None = None, exposure: float = ...,
                     offset: float | None = None) -> tuple[np.ndarray, np.ndarray]: ...


def _asked(tensor: torch.Tensor, ask: np.ndarray) -> np.ndarray:
    """The asked blocks of a device tensor, gathered to the host as float32 (the models run there)."""
    import torch

    return tensor[torch.from_numpy(ask).to(tensor.device)].to(torch.float32).cpu().numpy()


class LocalScorer:
    """A `learning.models.bundle.Model` in this process, judging by its stop rule at `offset`."""

    def __init__(self, model: Any, offset: float | None) -> None:
        self.model = model
        #: what the model reads: its two half buffers, features next to quick features, or blocks
        self.input = "halves" if getattr(model, "needs_halves", False) else \
            "features" if getattr(model, "input", "features") == "features" else "raw"
        self.rule: StopRule = model.rule(offset)

    def prepare(self, quick: np.ndarray, exposure: float, tally: Tally) -> np.ndarray:
        if self.input != "features":
            return quick
        from noisefeat import extract_features

        with torch_threads(1):
            feats = extract_features(np.ascontiguousarray(quick, np.float32), exposure=exposure)
        tally.add("feature_rows", len(quick))
        return feats

    def judge(self, batch: UnitBatch, ask: np.ndarray, quick: np.ndarray | None, exposure: float,
              tally: Tally) -> tuple[np.ndarray, np.ndarray]:
        """(verdict, ratio) of the asked blocks; a score is a signed distance, so the ratio is
        exp(offset - score). `quick`: what `prepare` made of the quick blocks, or None."""
        m, quick = self.model, None if quick is None else quick[ask]
        with torch_threads(1):
            with tally.timing():
                if self.input == "halves":
                    even, odd = (_asked(h, ask) for h in batch.halves)   # type: ignore[union-attr]
                    x = m.inputs_from_halves(even, odd, exposure)
                elif self.input == "features":
                    from learning.inputs.table import feature_input
                    from noisefeat import extract_features

                    x = feature_input(extract_features(_asked(batch.mean, ask), exposure=exposure), quick)
                else:
                    x = m.inputs_from_blocks(_asked(batch.mean, ask), quick, exposure=exposure)
            if self.input != "raw":
                tally.add("feature_rows", len(ask))
            score = np.asarray(m.decision_function(x), np.float64)
        with np.errstate(over="ignore"):
            ratio = np.exp(np.clip(self.rule.offset - score, -50, 50))
        return self.rule.verdict(score), ratio


class RemoteScorer:
    """A verdict server (`renderer.client.remote.RemoteModel`): it applies the stop rule at its
    model's offset or the `offset` sent; its verdicts are used as they come, with no ratio."""

    def __init__(self, model: Any, offset: float | None) -> None:
        self.model, self.offset, self.rule = model, offset, None

    def prepare(self, quick: np.ndarray, exposure: float, tally: Tally) -> np.ndarray:
        return quick

    def judge(self, batch: UnitBatch, ask: np.ndarray, quick: np.ndarray | None, exposure: float,
              tally: Tally) -> tuple[np.ndarray, np.ndarray]:
        m = self.model
        if getattr(m, "needs_halves", False):
            even, odd = (_asked(h, ask) for h in batch.halves)   # type: ignore[union-attr]
            verdict, _ = m.score_halves(even, odd, exposure=exposure, offset=self.offset)
        else:
            verdict, _ = m.score_blocks(_asked(batch.mean, ask), None if quick is None else
                                        np.asarray(quick, np.float32)[ask], exposure=exposure, offset=self.offset)
        verdict = np.asarray(verdict)
        if verdict.shape != (len(ask),):
            raise RuntimeError(f"model returned {verdict.shape} verdicts for {len(ask)} blocks")
        return np.where(verdict > 0, CONVERGED, NOISY), np.full(len(ask), np.nan)


@declare
class ModelCriterion(Criterion):
    """A learned verdict model, local or remote: flat blocks are converged without asking
    it, the others when their score exceeds the offset (the model's at `tau`, or `offset`).
    A `halves` model is asked from the second pass on, and a dotted block stays noisy.
    """

    name = "model"
    summary = "the learned model: a bundle, or a verdict server"
    #: the paper's block is its unit; given a smaller tile, it gates flip's (`renderer.criteria.gated`)
    grain = BLOCK
    settings = {"model": Setting(selects=True), "server": Setting(selects=True), "offset": Setting(selects=True)}

    def __init__(self, model: ScoresBlocks, exposure: float | None = None, offset: float | None = None,
                 tau: float | None = None) -> None:
        """`offset` None: the model's calibrated offset at `tau`, or its own without a tau."""
        if not hasattr(model, "score_blocks"):
            raise ValueError(f"model must have score_blocks(blocks, quick), got {type(model).__name__}")
        self.model = model
        given = self.checked(exposure=exposure, offset=offset, tau=tau)
        self.exposure = given["exposure"]
        #: the noise target (None: not given; the dot guard then holds at the default's)
        self.tau = None if tau is None else given["tau"]
        self._dots_tau = given["tau"]
        offset = given["offset"]
        if offset is None and tau is not None and hasattr(model, "offset_at"):
            offset = model.offset_at(self.tau)      # the model's calibrated offset at the noise target
        self.offset = None if offset is None else float(offset)
        self.needs_halves = bool(getattr(model, "needs_halves", False))
        self.needs_quick = not self.needs_halves and bool(
            getattr(model, "needs_quick", getattr(model, "input", "features") != "raw"))
        self.quick_kind = str(getattr(model, "quick", "albedo")) if self.needs_quick else "albedo"
        local = hasattr(model, "rule") and hasattr(model, "decision_function")
        self.scorer = LocalScorer(model, self.offset) if local else RemoteScorer(model, self.offset)

    @classmethod
    def from_spec(cls, spec: RenderSpec, thresholds: Sequence[int | None] | None = None) -> Criterion:
        """The model of `spec.model` (None: the bundled one) or `spec.server`, gating flip's
        tiles at tile grain."""
        if spec.server is not None:
            from ..client.remote import RemoteModel

            url, _, name = spec.server.partition("#")
            scorer: Any = RemoteModel(url, model=name or "default", tau=spec.tau)
            if not scorer.ready():             # unreachable: ConnectionError; refused: ValueError
                raise ConnectionError(f"{spec.server}: the server answers but model {scorer.model!r} is not ready")
        else:
            from learning.models.bundle import load_model

            scorer = load_model(spec.model)
        model = cls(scorer, exposure=spec.exposure, offset=spec.offset, tau=spec.tau)
        tile = spec.tile_grain()
        if tile is None:
            return model
        from .flip import FlipCriterion
        from .gated import GatedCriterion

        return GatedCriterion(model, FlipCriterion(exposure=spec.exposure, tau=spec.tau, tile=tile))

    @property
    def rule(self) -> StopRule | None:
        """The rule verdicts are made by here (None: a server's)."""
        return self.scorer.rule

    @property
    def effective_offset(self) -> float | None:
        """The offset verdicts are made at (None: a server's own)."""
        return self.rule.offset if self.rule is not None else self.offset

    def describe(self) -> dict[str, Any]:
        m = self.model
        d: dict[str, Any] = {"name": self.name, "offset": self.effective_offset, "tau": self.tau}
        manifest = getattr(m, "manifest", None)
        if isinstance(manifest, Mapping):
            d["model"] = {**{k: manifest.get(k) for k in ("kind", "name", "input", "quick")},
                          "path": str(getattr(m, "path", "") or "")}
        elif hasattr(m, "url"):
            d["model"] = {"remote": str(m.url), "name": str(getattr(m, "model", ""))}
        else:
            d["model"] = {"type": type(m).__name__}
        return d

    def prepare(self, quick: np.ndarray) -> tuple[np.ndarray, Tally]:
        """The quick blocks' features, once per render, for a local feature model."""
        tally = Tally()
        if not self.needs_quick:
            return quick, tally
        with tally.timing():
            out = self.scorer.prepare(np.asarray(quick, np.float32), self.exposure, tally)
        return out, tally

    def _decide(self, ids: list[int], batch: UnitBatch, tally: Tally) -> tuple[np.ndarray, np.ndarray]:
        flat = self._flat(batch, self.exposure, tally)
        ask = self._ready(batch, flat) if self.needs_halves else np.flatnonzero(~flat)
        verdict = np.full(len(ids), NOISY, np.int8)
        ratio = np.full(len(ids), np.nan)
        if ask.size:
            tally.add("units_featured", int(ask.size))
            quick = batch.quick if self.needs_quick else None     # a model without a quick image reads none
            verdict[ask], ratio[ask] = self.scorer.judge(batch, ask, quick, self.exposure, tally)
        dots = self._dots(batch, ask, self.exposure, self._dots_tau, tally) if self.needs_halves \
            else np.zeros(len(ids))
        ratio = np.where(flat, 0.0, np.where(dots > 1, np.fmax(ratio, dots), ratio))
        return hold_dotted(np.where(flat, CONVERGED, verdict), dots, flat), ratio
