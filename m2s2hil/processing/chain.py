"""The per-frame processing chain: dark subtraction → demosaicing → optional crosstalk + white reference.

``FrameProcessor`` is built once per capture configuration; every buffer it uses is allocated
then, so ``process`` allocates nothing per frame. The returned ``ProcessedFrame`` points into
those buffers: its cube and mask are overwritten by the next ``process`` call (copy to keep).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np

from m2s2hil.processing.calibration import CalibrationStep, CameraCalibration
from m2s2hil.processing.dark import MasterDark, subtract_dark
from m2s2hil.processing.demosaic import Demosaicer, get_demosaicer
from m2s2hil.processing.errors import FrameShapeError, ProcessingError
from m2s2hil.processing.mosaic import MosaicLayout
from m2s2hil.processing.stability import (
    check_phase,
    cube_saturation,
    low_light_warning,
    phase_warning,
    saturation_count_warning,
    saturation_warning,
)
from m2s2hil.processing.superpixel import SuperPixelDemosaicer

#: The QC checks (phase, low light) sample every 8th cell row of the corrected mosaic.
QC_ROW_STEP = 8


@dataclass
class ProcessedFrame:
    cube: np.ndarray  # float32 (bands, H', W'): DN after dark subtraction, or reflectance when calibrated
    saturated_mask: np.ndarray  # bool (H', W'): True where any band is unreliable because of clipping
    warnings: list[str] = field(default_factory=list)
    info: dict = field(default_factory=dict)  # method, dark and calibration provenance


class FrameProcessor:
    """Process raw uint16 mosaics with one method, one dark and one calibration.

    Not thread-safe: its buffers are shared by every call, so use one processor per thread.
    ``threads`` caps numba's worker threads for this processor's kernels (numba's setting is per
    calling thread, so other threads are unaffected). ``None`` uses every core, the fastest on an
    idle machine; 1 avoids waiting on a busy core, e.g. when capture and storage threads share
    the two cores with processing (see docs/benchmarks.md, single-thread table). Super-pixel runs
    dark, flags and demosaicing in one serial pass instead (``_process_fused``; docs/processing.md).
    The MSFA phase check (0.2–0.5 ms) runs on the first frame and then every
    ``check_phase_every`` frames (0: never): a phase error is a readout setting, not a per-frame event.
    """

    def __init__(
        self,
        method: str,
        camera_model,
        *,
        dark: MasterDark | None = None,
        calibration: CameraCalibration | None = None,
        check_phase_every: int = 16,
        threads: int | None = None,
    ) -> None:
        self.camera = camera_model
        pattern = (
            calibration.layout
            if calibration is not None and calibration.layout is not None
            else camera_model.layout
        )
        self.layout = MosaicLayout.from_pattern(pattern, camera_model.n_bands)
        self.shape = (camera_model.height, camera_model.width)
        self.full_scale = camera_model.full_scale
        self.demosaicer: Demosaicer = get_demosaicer(method, self.layout, self.shape)
        if dark is not None and dark.shape != self.shape:
            raise FrameShapeError(f"dark is {dark.shape}, camera frames are {self.shape}")
        self.dark = dark
        self.calibration = calibration
        self._cal = CalibrationStep(calibration, self.demosaicer) if calibration is not None else None
        if (
            self._cal is not None
            and self._cal.white_band_levels is not None
            and hasattr(self.demosaicer, "fix_gains")
        ):
            self.demosaicer.fix_gains(
                self._cal.white_band_levels
            )  # PPID balances with the white's band levels
        self._cube_sat = np.zeros(self.demosaicer.out_shape[1:], np.bool_)
        # super-pixel takes the one-pass path (no full corrected mosaic); the others the two-step one
        self._fused = self.demosaicer if isinstance(self.demosaicer, SuperPixelDemosaicer) else None
        if self._fused is None:
            self._corrected = np.empty(self.shape, np.uint16)
            self._raw_sat = np.empty(self.shape, np.bool_)
        else:
            n = self.layout.n
            self._qc_rows = np.empty((-(-self.shape[0] // n // QC_ROW_STEP), n, self.shape[1]), np.uint16)
        self._check_every = max(0, int(check_phase_every))
        most = int(numba.config.NUMBA_NUM_THREADS)  # type: ignore[attr-defined]  # set when numba loads
        if threads is not None and not 1 <= threads <= most:
            raise ProcessingError(f"threads must be 1..{most}, got {threads}")
        self.threads = threads
        self._count = 0
        self.info = {
            "method": method,
            "layout": [list(r) for r in self.layout.pattern],
            "dark": dark.provenance() if dark is not None else None,
            "calibration": calibration.provenance() if calibration is not None else None,
        }

    @property
    def method(self) -> str:
        return self.demosaicer.name

    def process(self, raw: np.ndarray) -> ProcessedFrame:
        if raw.shape != self.shape or raw.dtype != np.uint16:
            raise FrameShapeError(f"raw frame is {raw.dtype} {raw.shape}, expected uint16 {self.shape}")
        if self._fused is not None:
            return self._process_fused(raw, self._fused)
        if self.dark is not None:
            mosaic, sat = subtract_dark(
                raw, self.dark, out=self._corrected, sat_mask_out=self._raw_sat, full_scale=self.full_scale
            )
        else:
            mosaic = raw
            sat = np.greater_equal(raw, self.full_scale, out=self._raw_sat)
        if self.threads is None:
            cube = self.demosaicer.process(mosaic)
        else:
            before = numba.get_num_threads()
            numba.set_num_threads(self.threads)
            try:
                cube = self.demosaicer.process(mosaic)
            finally:
                numba.set_num_threads(before)
        warnings: list[str] = []
        if self._cal is not None:
            self._cal.apply(cube)
            warnings.extend(self._cal.warnings)
        if sat.any():
            cube_saturation(sat, self.demosaicer.name, self.layout.n, out=self._cube_sat)
            msg = saturation_warning(sat, self.full_scale, self.demosaicer.support_radius)
            if msg:
                warnings.append(msg)
        elif self._cube_sat.any():
            self._cube_sat.fill(False)
        if self._check_every and self._count % self._check_every == 0:
            msg = phase_warning(check_phase(mosaic, self.layout))
            if msg:
                warnings.append(msg)
        if self.dark is not None:
            msg = low_light_warning(mosaic, self.dark.read_noise_dn, self.layout.n)
            if msg:
                warnings.append(msg)
        self._count += 1
        return ProcessedFrame(cube=cube, saturated_mask=self._cube_sat, warnings=warnings, info=self.info)

    def _process_fused(self, raw: np.ndarray, sp: SuperPixelDemosaicer) -> ProcessedFrame:
        """Super-pixel in one pass with the dark and the saturation flags; the same frame as
        ``process``'s two-step path. The QC checks read only every ``QC_ROW_STEP``-th cell row,
        which the kernel keeps, so the corrected mosaic is never written whole."""
        raw = np.ascontiguousarray(raw)
        dark = self.dark.data if self.dark is not None else None
        qc = self._qc_rows if dark is not None else None
        cube, n_sat = sp.process_raw(raw, dark, self.full_scale, self._cube_sat, qc, QC_ROW_STEP)
        warnings: list[str] = []
        if self._cal is not None:
            self._cal.apply(cube)
            warnings.extend(self._cal.warnings)
        msg = saturation_count_warning(n_sat, raw.size, self.full_scale, sp.support_radius)
        if msg:
            warnings.append(msg)
        n = self.layout.n
        rows = raw if qc is None else qc.reshape(-1, self.shape[1])
        step = QC_ROW_STEP if qc is None else 1
        if self._check_every and self._count % self._check_every == 0:
            msg = phase_warning(check_phase(rows, self.layout, step=step))
            if msg:
                warnings.append(msg)
        if self.dark is not None:
            msg = low_light_warning(rows, self.dark.read_noise_dn, n, QC_ROW_STEP, row_step=step)
            if msg:
                warnings.append(msg)
        self._count += 1
        return ProcessedFrame(cube=cube, saturated_mask=self._cube_sat, warnings=warnings, info=self.info)
