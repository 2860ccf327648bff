"""What an adaptive render gives back in memory, with `save` writing the very files
`noisestop render` leaves."""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True, eq=False)
class RenderResult:
    """One finished adaptive render, all in memory (nothing is written until `save`).

    Parameters
    ----------
    image : numpy.ndarray
        float32 [H, W, 3], linear RGB: each pixel the mean of its block window's samples.
    spp : numpy.ndarray
        int64 [H, W], the samples per pixel each pixel got (its block's count).
    converged : numpy.ndarray
        bool [H, W], True where the criterion stopped the pixel's block before max_spp.
    report : dict
        The report.json object (settings, per-block spp and verdict history, totals,
        timings; `final_vs_reference` when a reference was given).
    reference : numpy.ndarray or None
        float32 [H, W, 3] reference image the report compares against, if any; `save`
        then also writes compare.png.
    """

    image: np.ndarray
    spp: np.ndarray
    converged: np.ndarray
    report: dict[str, Any]
    reference: np.ndarray | None = field(default=None, repr=False)

    def __repr__(self) -> str:
        h, w = self.image.shape[:2]
        return (f"RenderResult({w}x{h}, mean spp {float(self.spp.mean()):.1f}, "
                f"{int(self.report.get('blocks_converged', 0))} of {len(self.report.get('blocks', []))} "
                "blocks converged)")

    def save(self, directory: str | os.PathLike[str]) -> dict[str, str]:
        """Write final.exr (R, G, B plus the `spp` and `converged` channels), final.png,
        spp_map.png and report.json (and compare.png with a reference) into `directory`.

        Parameters
        ----------
        directory : str or os.PathLike
            Output folder; created if missing. An existing file there, or a folder that
            cannot be written, raises a one-line error before anything is written.

        Returns
        -------
        dict
            File name -> path of every file written.
        """
        from .outputs import prepare_output_dir, write_outputs

        out = prepare_output_dir(directory)
        return write_outputs(out, self.image, self.report, spp=self.spp, converged=self.converged,
                             reference=self.reference)
