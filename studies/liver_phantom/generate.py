"""Generate the shipped liver phantom meshes, print their quality, and draw the phantom figure.

    python studies/liver_phantom/generate.py [--output refsim/mesh/data]
        [--figure docs/figures/liver_phantom.png]

Needs the gmsh package (``pip install gmsh``). Each mesh is written as VTU (metres), read back through
refsim's loader (validation: positive volumes, closed outward boundary) and its quality printed.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from refsim.mesh import (
    LIVER_PHANTOM_RESOLUTIONS,
    generate_liver_phantom,
    is_closed_surface,
    mesh_quality,
    read_mesh,
    write_mesh,
)

ROOT = Path(__file__).resolve().parents[2]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", default=str(ROOT / "refsim" / "mesh" / "data"))
    parser.add_argument("--figure", default=str(ROOT / "docs" / "figures" / "liver_phantom.png"))
    args = parser.parse_args(argv)
    output = Path(args.output)
    output.mkdir(parents=True, exist_ok=True)
    for resolution, size in LIVER_PHANTOM_RESOLUTIONS.items():
        path = output / f"liver_phantom_{resolution}.vtu"
        write_mesh(path, generate_liver_phantom(size))
        mesh = read_mesh(path, fix_orientation=False)
        extent = 1e2 * np.ptp(mesh.rest_positions, axis=0)
        print(f"{resolution} (size {1e3 * size:g} mm) -> {path}")
        faces = mesh.boundary_faces
        a, b, c = (mesh.rest_positions[faces[:, k]] for k in range(3))
        # Outward faces: the volume they enclose (divergence theorem) equals the tets' (positive) volume.
        enclosed = np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0
        print(
            f"  extent {extent[0]:.1f} x {extent[1]:.1f} x {extent[2]:.1f} cm, volume "
            f"{1e3 * mesh.volumes.sum():.3f} L (boundary encloses {1e3 * enclosed:.3f} L), closed: "
            f"{is_closed_surface(faces)}, {faces.shape[0]} boundary faces"
        )
        print("  " + mesh_quality(mesh).format().replace("\n", "\n  "))
    if args.figure:
        from refsim.mesh import surface_patch
        from refsim.viz.phantom import render_phantom

        mesh = read_mesh(output / "liver_phantom_medium.vtu")
        # An example fixed patch: surface nodes within 3 cm of a point of the right lobe's posterior face.
        patch = surface_patch(
            mesh.rest_positions, mesh.boundary_faces, distance=0.03, point=(-0.04, -0.07, 0.0)
        )
        render_phantom(mesh, args.figure, highlight=patch)
        print(f"figure -> {args.figure}")


if __name__ == "__main__":
    main()
