"""A refnpr mesh export read by trimesh (an independent glTF reader).

    python3 scripts/check_mesh.py MESH.glb VERTICES TRIANGLES

Checks that trimesh loads one mesh with the vertex and triangle counts
refnpr reported, that it is watertight (every edge between two faces),
wound consistently with positive volume (normals outward), and that its
vertex colours span more than one grey. Exits 1 on a failure.
"""
import sys

import numpy as np
import trimesh


def main():
    path, vertices, triangles = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    scene = trimesh.load(path, force="scene", process=False)
    meshes = list(scene.geometry.values())
    if len(meshes) != 1:
        sys.exit(f"error: {path}: {len(meshes)} meshes, expected one")
    m = meshes[0]
    problems = []
    if len(m.vertices) != vertices or len(m.faces) != triangles:
        problems.append(f"{len(m.vertices)} vertices / {len(m.faces)} faces, refnpr wrote {vertices} / {triangles}")
    if not m.is_watertight:
        problems.append("not watertight")
    if not m.is_winding_consistent:
        problems.append("inconsistent winding")
    if m.volume <= 0:
        problems.append(f"volume {m.volume} (inward normals?)")
    # trimesh keeps a textured material's COLOR_0 as a vertex attribute.
    colours = np.asarray(m.visual.vertex_attributes["color"], dtype=np.float64)[:, :3]
    if colours.max() <= 1.0:
        colours = colours * 255.0  # float colours (linear, as glTF stores them)
    if len(colours) != len(m.vertices):
        problems.append(f"{len(colours)} vertex colours for {len(m.vertices)} vertices")
    elif colours.std(axis=0).max() < 5:
        problems.append(f"colours nearly constant (std {colours.std(axis=0)})")
    print(f"{path}: {len(m.vertices)} vertices, {len(m.faces)} faces, watertight {m.is_watertight}, "
          f"volume {m.volume:.4f}, colour range {colours.min():.0f}..{colours.max():.0f}")
    if problems:
        sys.exit("error: " + "; ".join(problems))


if __name__ == "__main__":
    main()
