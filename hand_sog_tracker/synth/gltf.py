"""Minimal reader of binary glTF 2.0 (``.glb``) skinned meshes.

Written for this package (no new dependency): it parses the GLB container
(12-byte header, a JSON chunk and a BIN chunk), resolves accessors through
their buffer views (``componentType``, ``type``, ``byteStride``,
``normalized``), walks the node hierarchy (``translation`` / ``rotation`` /
``scale`` or ``matrix``) and returns the first skinned mesh primitive:
``POSITION``, ``JOINTS_0``, ``WEIGHTS_0``, the triangle indices, the skin's
joints with their names, bind world matrices and ``inverseBindMatrices``.

Only what the hand meshes of :mod:`hand_sog_tracker.synth.mesh` need is
supported: one buffer embedded in the BIN chunk, triangle primitives (mode 4),
no sparse accessors, no morph targets.  Units are the file's (glTF: metres).
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.errors import InputError

__all__ = ["SkinnedMesh", "read_glb", "parse_glb", "accessor_array", "node_world_matrices"]

_GLB_MAGIC = 0x46546C67  # b"glTF"
_CHUNK_JSON = 0x4E4F534A
_CHUNK_BIN = 0x004E4942

_COMPONENT = {
    5120: np.int8,
    5121: np.uint8,
    5122: np.int16,
    5123: np.uint16,
    5125: np.uint32,
    5126: np.float32,
}
_N_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


@dataclass(frozen=True, eq=False)
class SkinnedMesh:
    """One skinned triangle mesh in its bind pose (file units, normally metres).

    Attributes
    ----------
    positions : array, shape (n, 3), float64
        Vertex positions in the mesh node's space.
    joints : int array, shape (n, 4)
        Skin-joint indices (into ``joint_names``) of each vertex's influences.
    weights : array, shape (n, 4), float64
        Influence weights, normalised to sum 1 per vertex.
    triangles : int array, shape (t, 3)
        Vertex indices of each triangle.
    joint_names : tuple of str, length j
        Node names of the skin joints.
    bind_matrices : array, shape (j, 4, 4)
        World matrices of the joints in the file's node hierarchy.
    inverse_bind_matrices : array, shape (j, 4, 4)
        The skin's ``inverseBindMatrices`` (identity if absent).
    mesh_matrix : array, shape (4, 4)
        World matrix of the node that holds the mesh.
    """

    positions: NDArray[np.float64]
    joints: NDArray[np.int64]
    weights: NDArray[np.float64]
    triangles: NDArray[np.int64]
    joint_names: tuple[str, ...]
    bind_matrices: NDArray[np.float64]
    inverse_bind_matrices: NDArray[np.float64]
    mesh_matrix: NDArray[np.float64]

    def joint_index(self, name: str) -> int:
        """Index of the joint called ``name``; raises :class:`InputError` if absent."""
        try:
            return self.joint_names.index(name)
        except ValueError:
            raise InputError(f"the mesh has no joint named {name!r}") from None

    def bind_positions(self) -> NDArray[np.float64]:
        """Joint positions (j, 3) of the bind pose: translations of ``inv(inverseBindMatrices)``."""
        return np.linalg.inv(self.inverse_bind_matrices)[:, :3, 3]


def accessor_array(gltf: dict[str, Any], binary: bytes, index: int) -> NDArray[Any]:
    """Read accessor ``index`` into an array of shape (count, components) (SCALAR: (count,)).

    Honours ``byteOffset`` of the accessor and its buffer view, ``byteStride``
    and ``normalized`` (integers mapped to [0, 1] / [-1, 1] as float64).  MAT4
    accessors come back as (count, 4, 4) in row-major order (glTF stores them
    column-major).
    """
    try:
        acc = gltf["accessors"][index]
    except (KeyError, IndexError):
        raise InputError(f"glTF accessor {index} does not exist") from None
    if "sparse" in acc:
        raise InputError("sparse glTF accessors are not supported")
    ctype = acc["componentType"]
    if ctype not in _COMPONENT:
        raise InputError(f"unsupported glTF componentType {ctype}")
    dtype = np.dtype(_COMPONENT[ctype]).newbyteorder("<")
    ncomp = _N_COMPONENTS[acc["type"]]
    count = int(acc["count"])
    if "bufferView" not in acc:
        out: NDArray[Any] = np.zeros((count, ncomp), dtype=dtype)
    else:
        view = gltf["bufferViews"][acc["bufferView"]]
        if view.get("buffer", 0) != 0:
            raise InputError("only the GLB's embedded buffer 0 is supported")
        start = int(view.get("byteOffset", 0)) + int(acc.get("byteOffset", 0))
        elem = dtype.itemsize * ncomp
        stride = int(view.get("byteStride", 0)) or elem
        end = start + stride * (count - 1) + elem
        if count and end > len(binary):
            raise InputError(f"glTF accessor {index} runs past the end of the binary chunk")
        raw = np.frombuffer(binary, dtype=np.uint8, count=end - start if count else 0, offset=start)
        if stride == elem:
            out = raw.view(dtype).reshape(count, ncomp)
        else:
            rows = np.lib.stride_tricks.as_strided(raw, shape=(count, elem), strides=(stride, 1))
            out = np.ascontiguousarray(rows).view(dtype).reshape(count, ncomp)
    if acc.get("normalized", False) and np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        out = np.maximum(out.astype(np.float64) / info.max, -1.0)
    if acc["type"] == "MAT4":
        return out.reshape(count, 4, 4).transpose(0, 2, 1).astype(np.float64)
    if acc["type"] == "MAT3":
        return out.reshape(count, 3, 3).transpose(0, 2, 1).astype(np.float64)
    return out[:, 0] if ncomp == 1 else out


def _quat_matrix(q: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation matrix (3, 3) of a glTF quaternion ``(x, y, z, w)`` (normalised first)."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _local_matrix(node: dict[str, Any]) -> NDArray[np.float64]:
    if "matrix" in node:
        return np.array(node["matrix"], dtype=np.float64).reshape(4, 4).T  # column-major
    m = np.eye(4)
    rs = _quat_matrix(np.array(node.get("rotation", [0.0, 0.0, 0.0, 1.0])))
    m[:3, :3] = rs * np.array(node.get("scale", [1.0, 1.0, 1.0]), dtype=np.float64)[None, :]
    m[:3, 3] = node.get("translation", [0.0, 0.0, 0.0])
    return m


def node_world_matrices(gltf: dict[str, Any]) -> NDArray[np.float64]:
    """World matrices (N, 4, 4) of all nodes (parent @ child through the hierarchy)."""
    nodes = gltf.get("nodes", [])
    parent = [-1] * len(nodes)
    for i, n in enumerate(nodes):
        for c in n.get("children", []):
            parent[c] = i
    world: list[NDArray[np.float64] | None] = [None] * len(nodes)

    def resolve(i: int, depth: int = 0) -> NDArray[np.float64]:
        if depth > len(nodes):
            raise InputError("the glTF node hierarchy has a cycle")
        w = world[i]
        if w is None:
            loc = _local_matrix(nodes[i])
            w = loc if parent[i] < 0 else resolve(parent[i], depth + 1) @ loc
            world[i] = w
        return w

    return np.array([resolve(i) for i in range(len(nodes))]).reshape(len(nodes), 4, 4)


def parse_glb(data: bytes) -> SkinnedMesh:
    """Parse the bytes of a ``.glb`` file and return its first skinned mesh primitive.

    Raises
    ------
    InputError
        Not a GLB 2.0 file, truncated, or no skinned triangle mesh in it.
    """
    if len(data) < 20:
        raise InputError("not a GLB file: too short")
    magic, version, length = struct.unpack_from("<III", data, 0)
    if magic != _GLB_MAGIC or version != 2:
        raise InputError(f"not a glTF 2.0 binary file (magic {magic:#x}, version {version})")
    if length > len(data):
        raise InputError(f"GLB file truncated: header says {length} bytes, got {len(data)}")
    gltf: dict[str, Any] | None = None
    binary = b""
    pos = 12
    while pos + 8 <= length:
        clen, ctype = struct.unpack_from("<II", data, pos)
        chunk = data[pos + 8 : pos + 8 + clen]
        if len(chunk) != clen:
            raise InputError("GLB chunk runs past the end of the file")
        if ctype == _CHUNK_JSON:
            gltf = json.loads(chunk.decode("utf-8"))
        elif ctype == _CHUNK_BIN and not binary:
            binary = chunk
        pos += 8 + clen + (-clen % 4)
    if gltf is None:
        raise InputError("GLB file has no JSON chunk")
    world = node_world_matrices(gltf)
    nodes = gltf.get("nodes", [])
    mesh_node = next((i for i, n in enumerate(nodes) if "mesh" in n and "skin" in n), None)
    if mesh_node is None:
        raise InputError("the glTF file has no skinned mesh node")
    prim = gltf["meshes"][nodes[mesh_node]["mesh"]]["primitives"][0]
    if prim.get("mode", 4) != 4:
        raise InputError("only triangle primitives (mode 4) are supported")
    attr = prim["attributes"]
    for key in ("POSITION", "JOINTS_0", "WEIGHTS_0"):
        if key not in attr:
            raise InputError(f"the mesh primitive has no {key}")
    pos_arr = accessor_array(gltf, binary, attr["POSITION"]).astype(np.float64)
    joints = accessor_array(gltf, binary, attr["JOINTS_0"]).astype(np.int64)
    weights = accessor_array(gltf, binary, attr["WEIGHTS_0"]).astype(np.float64)
    if "indices" in prim:
        idx = accessor_array(gltf, binary, prim["indices"]).astype(np.int64)
    else:
        idx = np.arange(pos_arr.shape[0], dtype=np.int64)
    if idx.size % 3:
        raise InputError("triangle index count is not a multiple of 3")
    skin = gltf["skins"][nodes[mesh_node]["skin"]]
    joint_nodes = list(skin["joints"])
    if "inverseBindMatrices" in skin:
        ibm = accessor_array(gltf, binary, skin["inverseBindMatrices"])
    else:
        ibm = np.repeat(np.eye(4)[None], len(joint_nodes), axis=0)
    wsum = weights.sum(axis=1, keepdims=True)
    if np.any(wsum <= 0):
        raise InputError("a vertex has no skin weight")
    if joints.max(initial=0) >= len(joint_nodes):
        raise InputError("JOINTS_0 refers to a joint the skin does not have")
    return SkinnedMesh(
        positions=pos_arr,
        joints=joints,
        weights=weights / wsum,
        triangles=idx.reshape(-1, 3),
        joint_names=tuple(str(nodes[j].get("name", f"node{j}")) for j in joint_nodes),
        bind_matrices=world[joint_nodes],
        inverse_bind_matrices=ibm,
        mesh_matrix=world[mesh_node],
    )


def read_glb(path: str | Path) -> SkinnedMesh:
    """Read a ``.glb`` file; see :func:`parse_glb`."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as err:
        raise InputError(f"cannot read {p}: {err}") from None
    return parse_glb(data)
