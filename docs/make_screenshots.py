"""Render the README's and the extension's screenshots off-screen into docs/images/.

    PYTHONPATH=. python docs/make_screenshots.py

Pictures of what the module and the CLI produce, rendered with BoneUSRecon's own
off-screen renderer (the Slicer GUI needs a display): a simulated clavicle phantom
reconstructed and coloured by Distance (the paper's Fig. 4), the same surface among
the sweep's image planes, and the default segmenter's contour on a frame of the real
PLUS recording shipped in Resources/SampleData.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "images"


def main() -> None:
    from BoneUSRecon.Logic.pipeline import reconstruct
    from BoneUSRecon.Logic.segmentation import segment_sweep
    from BoneUSRecon.Logic.sequence_io import read_sweep
    from BoneUSRecon.Logic.simulation import SimulationParams, simulate
    from BoneUSRecon.Widgets.overlay import overlay_image
    from BoneUSRecon.Widgets.render import render_views, save_png

    OUT.mkdir(parents=True, exist_ok=True)
    sim = simulate(SimulationParams(bone="clavicle", n_frames=100, corrupted_fraction=0.05, seed=0))
    recon = reconstruct(sim.sweep)
    top = render_views(
        recon.surface,
        points=recon.points,
        sweep=sim.sweep,
        views=("oblique",),
        window_size=(900, 420),
        fit_height=True,
    )["oblique"]
    save_png(top, OUT / "surface_distance.png")
    frames = render_views(
        recon.surface, sweep=sim.sweep, views=("oblique",), window_size=(900, 480), show_frames=True
    )["oblique"]
    save_png(frames, OUT / "sweep_planes.png")

    data = ROOT / "Resources" / "SampleData"
    real = read_sweep(
        data / "BoneUltrasound_L14.igs.mha", calibration=data / "BoneUltrasound_L14_config.xml"
    )
    seg = segment_sweep(real)
    c = seg.contours[len(seg.contours) // 2]
    img = overlay_image(
        real.frames[c.frame],
        c.points_px,
        accepted=c.accepted,
        label=f"BoneUltrasound_L14, frame {c.frame}: shadowpath contour",
    )
    save_png(np.asarray(img.resize((img.width // 2, img.height // 2))), OUT / "real_contour.png")
    for p in sorted(OUT.glob("*.png")):
        print(f"{p.relative_to(ROOT)}: {p.stat().st_size // 1024} KB")


if __name__ == "__main__":
    main()
