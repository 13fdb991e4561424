"""``bone-us-recon register SOURCE TARGET -o TRANSFORM``: rigid registration to a bone model."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from BoneUSRecon.cli.common import (
    SURFACE_HELP,
    add_common_options,
    add_json_option,
    check_distinct_paths,
    print_json,
    print_summary,
    removed_on_failure,
)

__all__ = [
    "register",
    "run",
    "add_registration_options",
    "registration_params",
]

TRANSFORM_HELP = (
    "output transform SOURCE->TARGET: .txt (4x4 matrix, row-major, mm) or .tfm/.h5 (ITK "
    "transform that 3D Slicer loads as a linear transform; see the README for the LPS and "
    "direction conventions)"
)


def add_registration_options(p: argparse.ArgumentParser, *, prefix: str = "") -> None:
    """Initial alignment and coordinate options, shared by ``register`` and
    ``reconstruct --register-to``."""
    p.add_argument(
        f"--{prefix}landmarks",
        nargs=2,
        metavar=("SRC.csv", "TGT.csv"),
        help="paired landmarks (CSV x,y,z in mm, the same points in the same order; at "
        "least 3, not on one line) for the initial alignment",
    )
    p.add_argument(
        f"--{prefix}init",
        metavar="MATRIX",
        help="initial SOURCE->TARGET transform (.txt 4x4 or .tfm/.h5); default the identity "
        "(the source is already roughly, within ~15 mm / 15 deg, in the model's frame)",
    )
    p.add_argument(
        f"--{prefix}search",
        action="store_true",
        help="no initial alignment known: search over the principal axes' ambiguities",
    )
    p.add_argument(
        "--ras",
        action="store_true",
        help="the inputs' coordinates are RAS, not LPS (only changes .tfm/.h5 files)",
    )


def registration_params(args: argparse.Namespace, prefix: str = "") -> Any:
    """:class:`RegistrationParams` from the options (the initial alignment method)."""
    from BoneUSRecon.Logic.errors import BoneUSReconError
    from BoneUSRecon.Logic.registration import RegistrationParams

    a = prefix.replace("-", "_")
    chosen = [n for n in ("landmarks", "init", "search") if getattr(args, a + n, None)]
    if len(chosen) > 1:
        raise BoneUSReconError(
            "choose one initial alignment: "
            + ", ".join(f"--{prefix}{n}" for n in chosen)
            + " were all given"
        )
    method = {"search": "search", "landmarks": "landmarks"}.get(
        chosen[0] if chosen else "", "identity"
    )
    return RegistrationParams(init=method)


def register(subparsers: Any) -> None:
    """Add the ``register`` sub-command."""
    p = subparsers.add_parser(
        "register",
        help="rigidly register a reconstructed surface (or points) to a bone model",
        description="Find the rigid transform mapping SOURCE coordinates (a reconstructed "
        "surface or segmented points) onto TARGET (a bone model from CT or MRI, in mm): "
        "an initial alignment (identity, --init, --landmarks or --search), then robust "
        "point-to-plane ICP. Prints the residuals, the inlier share and how well the "
        "surface constrains each degree of freedom; a result that should not be trusted "
        "(e.g. a featureless shaft that can slide along its axis) is flagged UNRELIABLE "
        "with the reasons.",
    )
    p.add_argument(
        "source",
        metavar="SOURCE",
        help=f"the reconstructed {SURFACE_HELP}, or points (.csv x,y,z mm)",
    )
    p.add_argument("target", metavar="TARGET", help=f"bone model {SURFACE_HELP}, in mm")
    p.add_argument("-o", "--output", required=True, metavar="TRANSFORM", help=TRANSFORM_HELP)
    add_registration_options(p)
    p.add_argument(
        "--registered",
        metavar="OUT",
        help="also write SOURCE moved into TARGET's frame (a surface: .vtp .vtk .ply .stl "
        ".obj; points: .vtp .vtk .ply .csv)",
    )
    add_json_option(p)
    add_common_options(p)
    p.set_defaults(func=run)


def read_source(path: str) -> tuple[Any, Any, Any]:
    """The source as ``(points (K, 3), normals or None, polydata or None)``."""
    import numpy as np
    from vtkmodules.util import numpy_support

    from BoneUSRecon.Logic.vtkio import read_points, read_polydata

    if Path(path).suffix.lower() in (".csv", ".txt"):
        return read_points(path), None, None
    pd = read_polydata(path)
    arr = pd.GetPointData().GetNormals()
    normals = numpy_support.vtk_to_numpy(arr).astype(float) if arr is not None else None
    return numpy_support.vtk_to_numpy(pd.GetPoints().GetData()).astype(np.float64), normals, pd


def run_registration(
    args: argparse.Namespace,
    points: Any,
    normals: Any,
    source_path: str | None,
    *,
    prefix: str = "",
    target: str,
    towards: Any = None,
) -> Any:
    """Read the model, landmarks and initial matrix named by the options; register."""
    from BoneUSRecon.Logic.registration import model_from_polydata
    from BoneUSRecon.Logic.registration import register as do_register
    from BoneUSRecon.Logic.transform_io import read_transform
    from BoneUSRecon.Logic.vtkio import read_points, read_polydata

    a = prefix.replace("-", "_")
    params = registration_params(args, prefix)
    model = model_from_polydata(read_polydata(target), target)
    coords = "RAS" if args.ras else "LPS"
    lm = getattr(args, a + "landmarks", None)
    landmarks = (read_points(lm[0]), read_points(lm[1])) if lm else None
    init_path = getattr(args, a + "init", None)
    init = read_transform(init_path, coordinates=coords) if init_path else None
    return do_register(
        points,
        model,
        params,
        source_normals=normals,
        towards_probe=towards,
        init=init,
        landmarks=landmarks,
        source_path=source_path,
        model_path=target,
    )


def warn_unreliable(reg: Any) -> None:
    """One stderr line when the result should not be trusted (the transform is still written)."""
    if not reg.reliable:
        print(
            f"bone-us-recon: warning: registration UNRELIABLE: {'; '.join(reg.reasons)}",
            file=sys.stderr,
        )


def run(args: argparse.Namespace) -> int:
    """Register SOURCE to TARGET; write the transform (and the moved source)."""
    from BoneUSRecon.Logic.errors import BoneUSReconError
    from BoneUSRecon.Logic.fileio import check_input_file, check_output_path
    from BoneUSRecon.Logic.registration import transform_polydata
    from BoneUSRecon.Logic.transform_io import TRANSFORM_EXTENSIONS, write_transform
    from BoneUSRecon.Logic.vtkio import (
        POINT_OUT_EXTENSIONS,
        SURFACE_EXTENSIONS,
        points_to_polydata,
        write_points,
        write_polydata,
    )

    inputs = [args.source, args.target, args.init, *(args.landmarks or [])]
    for f in inputs:
        if f:
            check_input_file(f)
    out = check_output_path(args.output, TRANSFORM_EXTENSIONS)
    moved_out = None
    if args.registered:
        moved_out = check_output_path(args.registered, {*SURFACE_EXTENSIONS, *POINT_OUT_EXTENSIONS})
    check_distinct_paths(
        inputs={
            "SOURCE": args.source,
            "TARGET": args.target,
            "--init": args.init,
            **{f"--landmarks ({k + 1})": f for k, f in enumerate(args.landmarks or [])},
        },
        outputs={"-o": args.output, "--registered": args.registered},
    )
    registration_params(args)  # conflicting options refused before any reading

    points, normals, pd = read_source(args.source)
    surface = pd is not None and pd.GetNumberOfPolys() + pd.GetNumberOfStrips() > 0
    if moved_out is not None:
        allowed = SURFACE_EXTENSIONS if surface else POINT_OUT_EXTENSIONS
        if moved_out.suffix.lower() not in allowed:
            raise BoneUSReconError(
                f"the source is a {'surface' if surface else 'point set'}: write it as one of "
                + ", ".join(allowed),
                moved_out,
            )
    reg = run_registration(args, points, normals, args.source, target=args.target)
    with removed_on_failure(out, moved_out):
        write_transform(reg.matrix, out, coordinates="RAS" if args.ras else "LPS")
        if moved_out is not None:
            moved = transform_polydata(
                pd if pd is not None else points_to_polydata(points), reg.matrix
            )
            (write_polydata if surface else write_points)(moved, moved_out)
    if args.json:
        print_json(
            {
                "output": str(out),
                "registered": str(moved_out) if moved_out else None,
                **reg.as_dict(),
            }
        )
    else:
        rows = list(reg.summary_rows())
        rows.append(("written", str(out)))
        if moved_out:
            rows.append(("registered source", str(moved_out)))
        print_summary(f"Registered {Path(args.source).name} to {Path(args.target).name}", rows)
    warn_unreliable(reg)
    return 0


# ---- reconstruct --register-to MODEL ---------------------------------------------------
def add_register_to_options(p: argparse.ArgumentParser) -> None:
    """``--register-to MODEL --transform-out TRANSFORM`` (+ initial alignment) for ``reconstruct``."""
    p.add_argument(
        "--register-to",
        metavar="MODEL",
        help="also register the reconstructed surface to this bone model (.vtp .vtk .stl .ply .obj, mm)",
    )
    p.add_argument(
        "--transform-out", metavar="TRANSFORM", help=f"with --register-to: the {TRANSFORM_HELP}"
    )
    add_registration_options(p, prefix="register-")


def check_register_to(args: argparse.Namespace, outputs: list[Any], inputs: list[Any]) -> Any:
    """Check the ``--register-to`` options before any work; the transform's output path or None."""
    from BoneUSRecon.Logic.errors import BoneUSReconError
    from BoneUSRecon.Logic.fileio import check_input_file, check_output_path
    from BoneUSRecon.Logic.transform_io import TRANSFORM_EXTENSIONS

    given = [
        n
        for n in ("register_landmarks", "register_init", "register_search", "transform_out")
        if getattr(args, n)
    ]
    if not args.register_to:
        if given:
            raise BoneUSReconError(f"--{given[0].replace('_', '-')} needs --register-to MODEL")
        return None
    if not args.transform_out:
        raise BoneUSReconError("--register-to needs --transform-out TRANSFORM (.txt, .tfm or .h5)")
    reg_inputs = [args.register_to, args.register_init, *(args.register_landmarks or [])]
    for f in reg_inputs:
        if f:
            check_input_file(f)
    out = check_output_path(args.transform_out, TRANSFORM_EXTENSIONS)
    check_distinct_paths(
        inputs=[*inputs, *reg_inputs], outputs=[*[str(o) for o in outputs if o], args.transform_out]
    )
    registration_params(args, "register-")
    return out


def register_reconstruction(args: argparse.Namespace, recon: Any, transform_out: Any) -> Any:
    """Register a reconstruction's segmented points to ``--register-to`` (see
    :func:`BoneUSRecon.Logic.registration.register_reconstruction` for why the points,
    each facing its probe); write the transform."""
    from BoneUSRecon.Logic.registration import towards_probe
    from BoneUSRecon.Logic.transform_io import write_transform
    from BoneUSRecon.Logic.vtkio import polydata_points

    towards = towards_probe(recon.points, recon.sweep.image_to_reference)
    reg = run_registration(
        args,
        polydata_points(recon.points),
        None,
        args.sweep,
        prefix="register-",
        target=args.register_to,
        towards=towards,
    )
    write_transform(reg.matrix, transform_out, coordinates="RAS" if args.ras else "LPS")
    return reg
