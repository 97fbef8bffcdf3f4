"""Registration and transfer: map a demo's scene onto the current one and warp its trajectory.

Modules: `tps` (thin-plate splines), `params` (settings in world units, presets, costs),
`kernel` (the compiled annealing loop), `sides` (clouds normalised and factorised for it),
`rpm` (bidirectional TPS-RPM for a pair or a batch), `chunks` (a scan's batches over worker
threads), `results` (what a pair or a scan returns), `library_scan` (one scene against the whole
library, cached), `transfer` (warping gripper poses), `planner` (register, warp and execute one
demo), `synthetic` (test clouds).
"""

from knotlab.core.registration.library_scan import LibraryRegistrar, library_digest, scan_library
from knotlab.core.registration.params import (
    COST_NAMES,
    EXACT,
    SCAN,
    RegistrationCosts,
    RegistrationParams,
    clean_cloud,
)
from knotlab.core.registration.results import Registration, ScanResult
from knotlab.core.registration.rpm import register

__all__ = [
    "COST_NAMES",
    "EXACT",
    "SCAN",
    "LibraryRegistrar",
    "Registration",
    "RegistrationCosts",
    "RegistrationParams",
    "ScanResult",
    "clean_cloud",
    "library_digest",
    "register",
    "scan_library",
]
