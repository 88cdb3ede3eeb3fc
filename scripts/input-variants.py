"""Meshes and point clouds as users send them, from the dev split's meshes, and back.

Usage: input-variants.py forward|back VARIANT IN.obj OUT.obj. `forward` makes the input a user
might send from a mesh (OBJ from `meshstream convert`) or from points with normals (OBJ from
`meshstream sample`); `back` takes a reconstruction of it (OBJ) back to the ground truth's frame,
so that `meshstream eval` scores it there. VARIANT is one of
  upright   the mesh as stored (y up);
  tipped    the mesh with z up, as CAD tools and Blender's exports often have it;
  mm        the mesh in millimetres, 12 metres off the origin;
  points    the points with their normals;
  bare      the points without normals (a scan's export);
  noisy05, noisy1, noisy2
            bare points moved by Gaussian noise of 0.5%, 1% or 2% of the longest side.
Noise is drawn from a seed made of the file's name, so a variant is the same on every run.
"""

import os
import sys
import zlib

import numpy as np

VARIANTS = ("upright", "tipped", "mm", "points", "bare", "noisy05", "noisy1", "noisy2")
NOISE = {"noisy05": 0.005, "noisy1": 0.01, "noisy2": 0.02}
MM_OFFSET = np.array([12000.0, -500.0, 250.0])


def read_obj(path):
    """The `v` rows, the `vn` rows and every other line, in order of kind."""
    vertices, normals, rest = [], [], []
    for line in open(path):
        head = line.split(maxsplit=1)[0] if line.strip() else ""
        if head == "v":
            vertices.append([float(x) for x in line.split()[1:4]])
        elif head == "vn":
            normals.append([float(x) for x in line.split()[1:4]])
        elif head:
            rest.append(line.rstrip("\n"))
    return np.array(vertices).reshape(-1, 3), np.array(normals).reshape(-1, 3), rest


def write_obj(path, vertices, normals, rest):
    with open(path, "w") as out:
        out.writelines(f"v {x:.7g} {y:.7g} {z:.7g}\n" for x, y, z in vertices)
        out.writelines(f"vn {x:.7g} {y:.7g} {z:.7g}\n" for x, y, z in normals)
        out.writelines(line + "\n" for line in rest)


def tip(rows):
    """y up to z up: (x, y, z) -> (x, -z, y)."""
    return np.stack([rows[:, 0], -rows[:, 2], rows[:, 1]], axis=1) if len(rows) else rows


def untip(rows):
    return np.stack([rows[:, 0], rows[:, 2], -rows[:, 1]], axis=1) if len(rows) else rows


def forward(variant, vertices, normals, name):
    if variant == "tipped":
        return tip(vertices), tip(normals)
    if variant == "mm":
        return vertices * 1000.0 + MM_OFFSET, normals
    if variant in NOISE:
        rng = np.random.default_rng(zlib.crc32(name.encode()))
        side = (vertices.max(axis=0) - vertices.min(axis=0)).max()
        vertices = vertices + rng.normal(0.0, NOISE[variant] * side, vertices.shape)
    if variant == "bare" or variant in NOISE:
        return vertices, normals[:0]
    return vertices, normals


def back(variant, vertices, normals):
    if variant == "tipped":
        return untip(vertices), untip(normals)
    if variant == "mm":
        return (vertices - MM_OFFSET) / 1000.0, normals
    return vertices, normals


def main(direction, variant, src, dst):
    if variant not in VARIANTS or direction not in ("forward", "back"):
        sys.exit(__doc__)
    vertices, normals, rest = read_obj(src)
    if direction == "forward":
        vertices, normals = forward(variant, vertices, normals, os.path.basename(src))
    else:
        vertices, normals = back(variant, vertices, normals)
    write_obj(dst, vertices, normals, rest)


if __name__ == "__main__":
    if len(sys.argv) != 5:
        sys.exit(__doc__)
    main(*sys.argv[1:])
