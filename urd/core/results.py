"""A scene's aligned stack and its methods' results: `Result` and the `SceneResults` part of
`urd.core.dataset.Scene` (the ingest record and the stack it aligned; results read, added, and
superseded by a new alignment)."""

from __future__ import annotations

import concurrent.futures
import copy
import dataclasses
from pathlib import Path
from typing import Any

from urd.core.errors import DatasetError, ManifestError
from urd.core.manifest import confined_path, now_iso, provenance, stale_note, stale_reason
from urd.core.shots import recorded_turns
from urd.core.swap import _final_name


@dataclasses.dataclass(frozen=True)
class Result:
    """A method's stored results: files by name (``R.tiff`` → path), the reference angle it was
    given (deg), warnings about its input (and that the results are stale, computed from an
    earlier alignment, when they are), the TIFF full scale, PSNR/SSIM against ground truth
    (virtual scenes), and the rest of its record (parameters, weights, time) as ``description``."""

    method: str
    files: dict[str, Path]
    reference_deg: float | None
    warnings: list[str]
    full_scale: float
    truth_metrics: dict | None
    description: dict


class SceneResults:
    """The aligned stack and the results of a `urd.core.dataset.Scene` (uses the scene's ``path``,
    ``name``, ``manifest_path``, ``_data``, ``check_files``, ``shots``, ``angles_deg``,
    ``is_complete``, ``capture_angles_deg`` and ``_commit``)."""

    def ingest_outcome(self) -> tuple[bool, str | None] | None:
        """(aligned?, the error when not) of the last ingest, or None before any."""
        ingest = self._data().get("ingest")
        return None if ingest is None else (ingest["ok"], ingest.get("error"))

    def is_ingested(self) -> bool:
        return "ingest" in self._data()

    def ingest_options(self) -> dict:
        """The options of the last ingest (empty before any); a polarization-camera frame's
        record its ``mosaic`` layout, ``demosaic`` and ``transfer``."""
        return copy.deepcopy(self._data().get("ingest", {}).get("options", {}))

    def methods(self) -> list[str]:
        """Methods whose results the scene holds."""
        return sorted(self._data().get("results", {}))

    def result(self, method: str, verify: bool = True) -> Result:
        """A method's results; with ``verify`` its files are checked against their hashes."""
        entry = self._data().get("results", {}).get(method)
        if entry is None:
            raise DatasetError(f"{self.name} has no results of {method!r} (results: {self.methods()})")
        if verify:
            self.check_files(entry["files"])
        files = {Path(f["file"]).name: confined_path(self.path, f["file"], str(self.manifest_path)) for f in entry["files"]}
        known = ("files", "reference_deg", "warnings", "full_scale", "truth_metrics", "stale")
        warnings = list(entry.get("warnings", [])) + ([f"STALE: {entry['stale']}"] if "stale" in entry else [])
        return Result(method, files, entry.get("reference_deg"), warnings,
                      float(entry.get("full_scale", 2.0)), copy.deepcopy(entry.get("truth_metrics")),
                      {k: copy.deepcopy(v) for k, v in entry.items() if k not in known})

    def results_dir(self, method: str) -> Path:
        return self.path / "results" / method

    def check_ingested(self) -> dict:
        """The scene's ingest record; DatasetError saying what to run where the capture is
        incomplete, not ingested, or failed to align."""
        ingest = self._data().get("ingest")
        if not self.is_complete():
            raise DatasetError(f"{self.name} is an incomplete capture ({len(self.shots())} of "
                               f"{len(self.capture_angles_deg() or [])} shots); resume it with 'urd capture {self.path.parent} --scene {self.name}' "
                               "and the options it was started with (urd ingest prints the whole command)")
        if not ingest:
            raise DatasetError(f"{self.name} is not ingested yet; run: urd ingest {self.path}")
        if not ingest["ok"]:
            raise DatasetError(f"{self.name}: {ingest['error']}")
        return ingest

    def load_stack(self, codes: bool = False) -> tuple["Any", list[float]]:
        """The aligned stack (N, H, W, 3) float32 linear, hash-verified, and its best known
        polarizer angles (deg); with ``codes`` the stored uint16 codes (65535 = 1.0; half the
        memory, `separate.optics.code_scale`). DatasetError unless it is ingested (`check_ingested`)."""
        import numpy as np
        import tifffile

        from urd.core.images import stored_tiff_layout, u16_to_linear

        ingest = self.check_ingested()
        try:
            self.check_files(ingest["aligned"])
        except ManifestError as exc:
            raise ManifestError(f"{exc}; the aligned shots are made again from the RAW shots by: "
                                f"urd ingest {self.path} --redo") from exc
        paths = [confined_path(self.path, f["file"], str(self.manifest_path)) for f in ingest["aligned"]]
        layouts = [stored_tiff_layout(path) for path in paths]
        if len(set(layouts)) != 1 or layouts[0][1] != np.uint16:
            raise DatasetError(f"{self.name}: the aligned shots are not one stack of 16-bit images of one size "
                               f"({', '.join(f'{shape} {dtype}' for shape, dtype in layouts)}); ingest the scene "
                               f"again: urd ingest {self.path} --redo")
        shape = layouts[0][0]
        if len(shape) != 3 or shape[2] != 3 or 0 in shape:               # urd writes RGB (grey as three equal channels)
            raise DatasetError(f"{self.name}: the aligned shots are of shape {shape}, expected H×W×3 (RGB); ingest "
                               f"the scene again: urd ingest {self.path} --redo")
        images = np.empty((len(paths),) + layouts[0][0], np.uint16 if codes else np.float32)

        def read(k: int) -> None:                  # into the stack itself: no second copy of a shot
            if codes:
                tifffile.imread(paths[k], out=images[k])
            else:
                u16_to_linear(tifffile.imread(paths[k]), out=images[k])

        with concurrent.futures.ThreadPoolExecutor(max_workers=2) as pool:     # the next file decodes meanwhile
            list(pool.map(read, range(len(paths))))
        return images, self.angles_deg()

    def set_ingest(self, ok: bool, options: dict, alignment: list | str, staged: dict[str, Path],
                   error: str | None = None, shot_hashes: list[str] | None = None) -> bool:
        """Record an ingest: staged aligned files (final name → staged path) are swapped in;
        aligned files of an earlier ingest that are no longer named are removed. What was
        computed from an earlier alignment is superseded: results are marked stale (kept, with
        the command that renews them), a per-shot angle calibration is removed (its record and
        the calibrated angles are kept in the provenance); an alignment giving the very same
        aligned files (by SHA-256) at the same angles supersedes nothing.

        A failed ingest (``ok`` false) of a scene whose earlier ingest aligned changes nothing but
        the provenance, where the attempt and its error are recorded: the earlier aligned shots,
        results and calibration stay. Returns whether the ingest was recorded as the scene's."""
        earlier = self._data().get("ingest")
        if not ok and earlier is not None and earlier["ok"]:
            def note(_: list[dict]) -> None:
                self._data()["provenance"].append(provenance("ingest failed, the earlier alignment kept",
                                                              {**options, "error": error}))

            self._commit({}, note)
            return False
        record = {"time": now_iso(), "ok": ok, "options": options, "alignment": alignment, "aligned": []}
        if error is not None:
            record["error"] = error
        if shot_hashes:
            record["shot_hashes"] = shot_hashes

        def change(files: list[dict]) -> None:
            data = self._data()
            before = data.get("ingest") or {}
            same = (before.get("ok") and [f["sha256"] for f in before.get("aligned", [])] == [f["sha256"] for f in files]
                    and recorded_turns(before.get("alignment")) == recorded_turns(alignment))
            earlier = self._supersede(data) if "ingest" in data and not same else None    # the same stack: nothing to renew
            data["ingest"] = {**record, "aligned": files}
            data["ingest"]["angles_deg"] = self.angles_deg()              # in the new alignment's frame
            if earlier:
                data["provenance"].append(provenance("supersede", earlier))
            data["provenance"].append(provenance("ingest", options))

        self._commit(staged if ok else {}, change)
        return True

    def _supersede(self, data: dict) -> dict:
        """Mark results stale and remove the per-shot calibration of ``data`` (before a new
        alignment); returns what was superseded, for the provenance (empty when nothing)."""
        earlier = {}
        for method, entry in data.get("results", {}).items():     # the newest reason: the earlier ones no longer hold
            entry["stale"] = stale_note(self.path, method, "computed from an earlier alignment (the scene was ingested again)")
            earlier.setdefault("stale_results", []).append(method)
        if "calibration" in data:
            earlier["calibration"] = data.pop("calibration")
            earlier["angles_calibrated_deg"] = [s.get("angle_calibrated_deg") for s in data["shots"]]
            for shot in data["shots"]:
                shot["angle_calibrated_deg"] = None
        if earlier:
            earlier["reason"] = "computed from the earlier alignment"
        return earlier

    def stale_reason(self, method: str) -> str | None:
        """Why the manifest marks ``method``'s results stale (`urd.core.manifest.stale_reason`), or None."""
        note = self._data().get("results", {}).get(method, {}).get("stale")
        return None if note is None else stale_reason(note)

    def check_no_results(self, method: str) -> None:
        """DatasetError if the manifest already records results of ``method``, or its results folder
        holds files the manifest does not list (replacing them takes --force). What a killed run
        left unfinished is finished first (taking the dataset's lock does it), so that the answer is
        about the scene as it stands."""
        if self.unfinished_swap() is not None:
            with self.lock():
                self.reload()
        if method in self.methods():
            stale = self.stale_reason(method)
            what = f"STALE {method} results ({stale})" if stale else f"{method} results"
            raise DatasetError(f"{self.name} already has {what} ({self.results_dir(method)}); pass --force to replace them")
        folder = self.results_dir(method)
        unlisted = sorted(p.name for p in folder.iterdir() if not p.name.startswith(".")) if folder.is_dir() else []
        if unlisted:
            raise DatasetError(f"{folder} holds files no manifest lists ({', '.join(unlisted[:3])}"
                               f"{', …' if len(unlisted) > 3 else ''}); move them away, or pass --force to replace them")

    def add_result(self, method: str, staged: dict[str, Path], entry: dict, replace: bool = False) -> Result:
        """Record a method's results: staged files (final name → staged path) are swapped in
        over the previous results (only with ``replace``); ``entry`` holds the method's
        description (parameters, weights, metrics). Returns the stored entry."""
        if not replace:
            self.check_no_results(method)
        base = {**entry, "time": now_iso(), "method": method}

        def change(files: list[dict]) -> None:
            data = self._data()
            data.setdefault("results", {})[method] = {**base, "files": files}
            data["provenance"].append(provenance(f"separate {method}", entry.get("parameters", {})))

        self._commit(staged, change)
        return self.result(method, verify=False)

    def add_result_files(self, method: str, staged: dict[str, Path], step: str) -> Result:
        """Add staged files (final name → staged path) to a method's stored results, e.g. the
        polarization maps computed afterwards; files of the same name are replaced, the rest of
        the record kept. ``step`` names the work in the provenance. Returns the stored entry."""
        if method not in self.methods():
            raise DatasetError(f"{self.name} has no results of {method!r} to add to (results: {self.methods()})")

        def change(files: list[dict]) -> None:
            entry = self._data()["results"][method]
            added = {_final_name(rec["file"]) for rec in files}
            entry["files"] = [rec for rec in entry["files"] if rec["file"] not in added] + files
            self._data()["provenance"].append(provenance(step, {"method": method}))

        self._commit(staged, change)
        return self.result(method, verify=False)
