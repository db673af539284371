"""Recovery: the solver parts behind :func:`polarshape.normals.recover_normals` (no orchestration here).

Along the data flow:

- :mod:`~polarshape.recover.observations` — :class:`RecoveryInputs` (images) and :class:`Observations`
  (flat per-pixel batches), pyramid and crop;
- :mod:`~polarshape.recover.preprocess` — capture → :class:`RecoveryInputs`;
- :mod:`~polarshape.recover.photometric` — Lambertian photometric stereo (plain and robust): the initial normals;
- :mod:`~polarshape.recover.reflectometry` — the material for known normals (spec eq. 25);
- :mod:`~polarshape.recover.table_fit` — the material of a tabulated (MERL-layout) BRDF, log-RMSE;
- :mod:`~polarshape.recover.normal_solver` — per-pixel Levenberg–Marquardt normals, neighbour propagation;
- :mod:`~polarshape.recover.priors` — smoothness prior, filling pixels without data;
- :mod:`~polarshape.recover.joint_solve` — normals and material in one Levenberg–Marquardt (Schur complement);
- :mod:`~polarshape.recover.coarse_to_fine` — material and normals alternated (or solved jointly) on a pyramid;
- :mod:`~polarshape.recover.options` — the options, embedded in ``polarshape run``'s config.
"""

from polarshape.recover.coarse_to_fine import FMBRDFState, SolveLog, solve_fmbrdf
from polarshape.recover.normal_solver import NormalProblem, propagate_normals, refine_normals
from polarshape.recover.observations import Observations, RecoveryInputs
from polarshape.recover.options import InitialNormalsOptions, RecoveryOptions
from polarshape.recover.photometric import PSReason, RobustPSResult, lambertian_ps, robust_lambertian_ps
from polarshape.recover.preprocess import preprocess_capture
from polarshape.recover.reflectometry import ReflectanceFit, fit_reflectance
from polarshape.recover.table_fit import TableFit, fit_fmbrdf_to_table, fit_material_table

__all__ = [
    "FMBRDFState",
    "InitialNormalsOptions",
    "NormalProblem",
    "Observations",
    "PSReason",
    "RecoveryInputs",
    "RecoveryOptions",
    "ReflectanceFit",
    "RobustPSResult",
    "SolveLog",
    "TableFit",
    "fit_fmbrdf_to_table",
    "fit_material_table",
    "fit_reflectance",
    "lambertian_ps",
    "preprocess_capture",
    "propagate_normals",
    "refine_normals",
    "robust_lambertian_ps",
    "solve_fmbrdf",
]
