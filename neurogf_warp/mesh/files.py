"""Mesh files read in the file's own vertex numbering: OBJ (own reader), PLY and STL (trimesh, checked).

``read_mesh_file(path)`` returns every vertex record of the file, in file order, and the faces as triangles
indexing them. Nothing is dropped, merged or reordered here: unreferenced vertices stay (trimesh's OBJ reader
drops them, which shifts every later index), and STL keeps its three corners per triangle (welding is
``neurogf_warp.mesh.mesh``'s job). Every error is an ``InputError`` (a ``ValueError``) naming the file and what is
wrong with it.

Text (OBJ, ASCII PLY) may be UTF-8 with or without a byte-order mark, UTF-16 or UTF-32 with one, and end its
lines in LF, CRLF or CR; bytes that are not UTF-8 are accepted in comments and other records that carry no
geometry. An ASCII PLY body is checked record by record against its header, so a truncated file, or one with
more data than its header declares, is refused rather than read short.
"""
from __future__ import annotations

import os
import re

import numpy as np

from neurogf_warp.common.checks import InputError

__all__ = ["read_mesh_file", "MESH_SUFFIXES"]

# Suffixes read here; anything else goes to trimesh's own loaders as given.
MESH_SUFFIXES = (".obj", ".ply", ".stl")
# Archives holding one mesh file, and single compressed files, opened here so their mesh keeps its numbering.
ARCHIVE_SUFFIXES = (".zip", ".tar", ".tar.gz", ".tgz", ".tar.bz2", ".tbz2", ".tar.xz", ".txz")
COMPRESSED_SUFFIXES = (".gz", ".bz2", ".xz")
# Bytes looked at to tell text from binary data.
SNIFF_BYTES = 4096
INT64_MIN, INT64_MAX = -2**63, 2**63 - 1


def read_mesh_file(path) -> tuple[np.ndarray, np.ndarray, str]:
    """Read a mesh file's vertex records and triangles in the file's own order.

    Parameters
    ----------
    path : str or os.PathLike
        An ``.obj``, ``.ply`` or ``.stl`` file (other formats are passed to ``trimesh.load``); or an archive
        (``.zip``, ``.tar``, ``.tar.gz``/``.tgz``, ``.tar.bz2``/``.tbz2``, ``.tar.xz``/``.txz``) holding exactly one
        mesh file, or one compressed mesh file (``bunny.obj.gz``, ``.bz2``, ``.xz``), read by the same readers.

    Returns
    -------
    vertices : (n, 3) float64, file units
        One row per vertex record of the file, in file order (for STL, three per triangle, unwelded).
    faces : (F, 3) int64
        Triangles indexing ``vertices``; polygons are split into triangles (quads along their first
        diagonal, larger polygons as a fan from their first corner).
    kind : str
        ``"obj"``, ``"ply"``, ``"stl"`` or the suffix of another format (of the mesh inside an archive).

    Raises
    ------
    FileNotFoundError
        When nothing exists at ``path``.
    ValueError
        When the file is not a mesh of its kind (the message names the file, and the line for OBJ), or not a
        regular file (a folder, a device such as ``/dev/null``, a FIFO).
    """
    from neurogf_warp.common.files import check_input_file, note_input

    path = os.fspath(path)
    if os.path.isdir(path):
        raise InputError(f"{path} is a folder, not a mesh file")
    check_input_file(path, "mesh file", note=False)
    name = os.path.basename(path).lower()
    archive = next((a for a in ARCHIVE_SUFFIXES if name.endswith(a)), None)
    packed = next((c for c in COMPRESSED_SUFFIXES if name.endswith(c)), None)
    where = path
    if archive is not None:
        data, member = _archive_member(path, archive)
        kind, where = _suffix(member), f"{path} ({member})"
    else:
        with open(path, "rb") as fh:
            data = fh.read()
        if packed is not None:
            data = _decompress(data, packed, path)
            name = name[:-len(packed)]
        kind = _suffix(name)
    if not data.strip():
        raise InputError(f"mesh file {where} is empty")
    if kind == "obj":
        v, f = _read_obj(data, where)
    elif kind == "ply":
        v, f = _read_ply(data, where)
    elif kind == "stl":
        v, f = _read_stl(data, where)
    else:
        v, f = _read_other(data, kind, where)
    if len(f) == 0:
        raise InputError(f"mesh file {where} has no triangle faces: NeuroGF needs a triangle surface")
    note_input(path)  # an input of this command now: no output of it may replace the file
    return v, f, kind


def _suffix(name: str) -> str:
    return os.path.splitext(name)[1].lower().lstrip(".")


def _formats_message() -> str:
    """The formats ``read_mesh_file`` reads, for error messages."""
    import trimesh

    other = sorted(set(trimesh.available_formats()) - {"obj", "ply", "stl", "stl_ascii", "zip", "bz2", "tar.gz",
                                                       "tar.bz2"})
    return (f".obj, .ply, .stl, {', '.join('.' + o for o in other)} (through trimesh); an archive "
            f"({', '.join(ARCHIVE_SUFFIXES)}) holding one of these; or one compressed mesh file "
            f"({', '.join('.obj' + c for c in COMPRESSED_SUFFIXES)}, ...)")


def _decompress(data: bytes, suffix: str, path: str) -> bytes:
    import bz2
    import gzip
    import lzma

    try:
        return {".gz": gzip.decompress, ".bz2": bz2.decompress, ".xz": lzma.decompress}[suffix](data)
    except (OSError, EOFError, ValueError, lzma.LZMAError) as e:
        raise InputError(f"{path} is not a valid {suffix} compressed file ({e})") from None


def _archive_member(path: str, suffix: str) -> tuple[bytes, str]:
    """The bytes and name of the one mesh file in an archive (read by our own readers, in file order)."""
    import tarfile
    import zipfile

    def is_mesh(name: str) -> bool:
        base = os.path.basename(name)
        return bool(base) and not base.startswith(".") and _suffix(base) in _member_kinds()

    try:
        if suffix == ".zip":
            with zipfile.ZipFile(path) as z:
                names = [i.filename for i in z.infolist() if not i.is_dir() and is_mesh(i.filename)]
                if len(names) == 1:
                    return z.read(names[0]), names[0]
        else:
            with tarfile.open(path, "r:*") as t:
                members = [m for m in t.getmembers() if m.isfile() and is_mesh(m.name)]
                names = [m.name for m in members]
                if len(names) == 1:
                    return t.extractfile(members[0]).read(), names[0]
    except (zipfile.BadZipFile, tarfile.TarError, OSError, EOFError) as e:
        raise InputError(f"{path} is not a valid {suffix} archive ({e})") from None
    if not names:
        kinds = ", ".join("." + k for k in _member_kinds())
        raise InputError(f"archive {path} holds no mesh file (looked for {kinds})")
    raise InputError(f"archive {path} holds {len(names)} mesh files ({', '.join(names[:5])}"
                     f"{' ...' if len(names) > 5 else ''}); give an archive with one mesh, or the mesh file itself")


def _member_kinds() -> list[str]:
    import trimesh

    return sorted(({"obj", "ply", "stl"} | set(trimesh.available_formats()))
                  - {"zip", "bz2", "tar.gz", "tar.bz2", "stl_ascii"})


# --- OBJ ------------------------------------------------------------------------------------------------------

# Byte-order marks of the text encodings an OBJ may come in, longest first (UTF-32 LE starts like UTF-16 LE).
_BOMS = ((b"\xff\xfe\x00\x00", "utf-32-le"), (b"\x00\x00\xfe\xff", "utf-32-be"), (b"\xef\xbb\xbf", "utf-8"),
         (b"\xff\xfe", "utf-16-le"), (b"\xfe\xff", "utf-16-be"))
# Control characters allowed in text: tab, LF, vertical tab, form feed, CR (and ESC, DEL are not).
_TEXT_CONTROLS = frozenset(b"\t\n\x0b\x0c\r")
# Fraction of other control bytes above which the data is binary, not text with a stray byte.
MAX_CONTROL_FRACTION = 0.01


def _decode_text(data: bytes, path: str, kind: str) -> str:
    """The text of a text-format mesh file: a byte-order mark chooses UTF-8/16/32 (and is dropped); otherwise
    UTF-8, where bytes that are not UTF-8 (e.g. a Latin-1 letter in a comment) become U+FFFD. Binary data (NUL
    bytes, or many control bytes) is refused."""
    for bom, encoding in _BOMS:
        if data.startswith(bom):
            try:
                return data[len(bom):].decode(encoding)
            except UnicodeDecodeError as e:
                raise InputError(f"{path}: the file starts with a {encoding.upper()} byte-order mark but is not "
                                 f"{encoding.upper()} text (byte {e.start + len(bom)}); save it as UTF-8 text") from None
    head = data[:SNIFF_BYTES]
    controls = sum(1 for b in head if b < 32 and b not in _TEXT_CONTROLS)
    if b"\x00" in head or controls > MAX_CONTROL_FRACTION * len(head):
        # UTF-16 text without a byte-order mark: every other byte of ASCII characters is NUL
        utf16 = max(head[0::2].count(0), head[1::2].count(0)) > 0.4 * len(head) / 2
        hint = " (if it is UTF-16 text without a byte-order mark, save it as UTF-8)" if utf16 else ""
        raise InputError(f"{path} is not a mesh file: it holds binary data, and an {kind.upper()} file is text "
                         f"(check that the file is not truncated, compressed or of another format){hint}")
    return data.decode("utf-8", errors="replace")


def _read_obj(data: bytes, path: str):
    text = _decode_text(data, path, "obj")
    # a backslash at the end of a line continues it on the next one
    text = re.sub(r"\\\r?\n", " ", text)
    coords: list = []    # 3 coordinate strings per vertex record
    v_lines: list = []
    corners: list = []   # index strings of every face corner
    counts: list = []    # corners per face
    seen: list = []      # vertex records read before each face (for relative indices)
    f_lines: list = []
    for lineno, line in enumerate(text.splitlines(), 1):
        if "#" in line:
            line = line[:line.index("#")]
        tok = line.split()
        if not tok:
            continue
        key = tok[0]
        if key == "v":
            if len(tok) < 4:
                raise InputError(f"{path}, line {lineno}: a vertex record needs 3 coordinates, got {len(tok) - 1}")
            coords += tok[1:4]
            v_lines.append(lineno)
        elif key == "f":
            if len(tok) < 4:
                raise InputError(f"{path}, line {lineno}: a face needs at least 3 vertices, got {len(tok) - 1}")
            corners += tok[1:]
            counts.append(len(tok) - 1)
            seen.append(len(v_lines))
            f_lines.append(lineno)
        # other records (vt, vn, g, o, s, usemtl, l, ...) carry no triangle topology
    if not v_lines:
        raise InputError(f"{path} is not a mesh file: it has no vertex records ('v x y z' lines)")
    if not f_lines:
        raise InputError(f"mesh file {path} has no faces ('f' lines): NeuroGF needs a triangle surface")
    n = len(v_lines)
    try:
        verts = np.array(coords, dtype=np.float64).reshape(n, 3)
    except ValueError:
        bad = next(i for i, c in enumerate(coords) if not _parses(float, c))
        raise InputError(f"{path}, line {v_lines[bad // 3]}: vertex coordinate {coords[bad]!r} is not a number") from None
    counts = np.asarray(counts, dtype=np.int64)
    face_of = np.repeat(np.arange(len(counts)), counts)  # face of each corner
    corners = [c.split("/", 1)[0] if "/" in c else c for c in corners]
    try:
        idx = np.array(corners, dtype=np.int64)
    except (ValueError, OverflowError):
        for i, c in enumerate(corners):
            if not _parses(int, c):
                raise InputError(f"{path}, line {f_lines[face_of[i]]}: face vertex {c!r} is not an index") from None
            if not INT64_MIN <= int(c) <= INT64_MAX:  # a valid integer, but no file has that many vertices
                raise InputError(f"{path}, line {f_lines[face_of[i]]}: vertex index {c} is out of range: the file has "
                                 f"{n} vertex records") from None
        raise
    before = np.asarray(seen, dtype=np.int64)[face_of]
    # OBJ indices are 1-based; negative ones are relative: -1 is the last vertex defined before the face
    k = np.where(idx > 0, idx - 1, idx + before)
    bad = (idx == 0) | (k < 0) | (k >= n)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        where = f"{path}, line {f_lines[face_of[i]]}"
        if idx[i] == 0:
            raise InputError(f"{where}: vertex index 0 is not valid (OBJ indices start at 1)")
        if idx[i] < 0:
            raise InputError(f"{where}: relative index {idx[i]} points before the first vertex "
                             f"({before[i]} defined before this face)")
        raise InputError(f"{where}: vertex index {idx[i]} is out of range: the file has {n} vertex records")
    return verts, _triangulate(k, counts)


def _parses(convert, s: str) -> bool:
    try:
        convert(s)
    except ValueError:
        return False
    return True


def _triangulate(k: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Faces of ``counts`` corners each (flat ``k``) as triangles, in face order."""
    if np.all(counts == 3):
        return k.reshape(-1, 3)
    if np.all(counts == 4):
        q = k.reshape(-1, 4)
        # trimesh lists all first halves of the quads before the second halves; the same order keeps the
        # fingerprints (and so the model files) of quad meshes loaded through trimesh before this reader
        return np.concatenate([q[:, [0, 1, 2]], q[:, [2, 3, 0]]])
    tris = []
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    for s, c in zip(starts.tolist(), counts.tolist()):
        p = k[s:s + c].tolist()
        if c == 4:
            tris += [[p[0], p[1], p[2]], [p[2], p[3], p[0]]]
        else:  # a fan from the first corner
            tris += [[p[0], p[i], p[i + 1]] for i in range(1, c - 1)]
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


# --- PLY ------------------------------------------------------------------------------------------------------

_PLY_TYPES = {"char": "i1", "uchar": "u1", "int8": "i1", "uint8": "u1", "short": "i2", "ushort": "u2",
              "int16": "i2", "uint16": "u2", "int": "i4", "uint": "u4", "int32": "i4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_PLY_FACE_LISTS = ("vertex_indices", "vertex_index")


def _ply_header(data: bytes, path: str) -> tuple[str, list, int]:
    """(encoding, elements as [name, count, [(property, type) or (property, count type, item type)]], header bytes)."""
    if not data.startswith(b"ply"):
        raise InputError(f"{path} is not a mesh file: a PLY file starts with 'ply' (found {data[:12]!r})")
    end = data.find(b"end_header")
    if end < 0:
        raise InputError(f"{path} is not a valid PLY file: its header has no 'end_header' line")
    nl = data.find(b"\n", end)
    header_len = len(data) if nl < 0 else nl + 1
    enc, elements = None, []
    for line in data[:end].decode("ascii", errors="replace").splitlines():
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "format" and len(tok) >= 2:
            enc = tok[1]
        elif tok[0] == "element" and len(tok) >= 3:
            try:
                count = int(tok[2])
            except ValueError:
                raise InputError(f"{path}: PLY element {tok[1]!r} has a count {tok[2]!r} that is not a number") from None
            if count < 0:
                raise InputError(f"{path}: PLY element {tok[1]!r} has a negative count {count}")
            elements.append([tok[1], count, []])
        elif tok[0] == "property" and elements:
            types = tok[2:4] if len(tok) >= 5 and tok[1] == "list" else tok[1:2]
            if len(types) not in (1, 2) or any(t not in _PLY_TYPES for t in types):
                raise InputError(f"{path}: PLY property line {line.strip()!r} has an unknown type")
            elements[-1][2].append((tok[-1], *types))
    if enc not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputError(f"{path}: unknown PLY format {enc!r} (expected ascii or binary_little/big_endian)")
    if not any(e[0] == "vertex" for e in elements):
        raise InputError(f"{path}: the PLY header declares no vertex element")
    return enc, elements, header_len


def _read_ply(data: bytes, path: str):
    enc, elements, header_len = _ply_header(data, path)
    n_vert = next(e[1] for e in elements if e[0] == "vertex")
    body = len(data) - header_len
    if enc == "ascii":
        _check_ply_ascii(data[header_len:], elements, path)
    else:
        need = sum(e[1] * sum(np.dtype(_PLY_TYPES[p[1]]).itemsize for p in e[2]) for e in elements
                   if all(len(p) == 2 for p in e[2]))
        if need > body:
            raise InputError(f"{path}: the PLY header declares {need} bytes of fixed-size records but only {body} "
                             "bytes follow it: the file is truncated or corrupt")
    # trimesh splits vertices along seams when faces carry lists besides their corners (per-corner texture
    # coordinates), which changes the vertex count and numbering: such files are read record by record here
    extra = any(len(p) == 3 and not (name == "face" and p[0] in _PLY_FACE_LISTS) for name, _, props in elements
                for p in props)
    v = None
    if not extra:
        try:
            v, f = _trimesh_arrays(data, "ply", path)
        except ValueError:
            if enc == "ascii":
                raise
        if v is not None and len(v) != n_vert:
            v = None
    if v is None:
        if enc == "ascii":
            v, f = _ply_ascii(data[header_len:], elements, path)
        else:  # also binary polygon lists of several lengths, which trimesh does not read
            v, f = _ply_binary(data, header_len, elements, "<" if enc == "binary_little_endian" else ">", path)
    if len(v) != n_vert:
        raise InputError(f"{path}: the PLY header declares {n_vert} vertices but {len(v)} were read")
    return v, f


def _ply_ascii(body: bytes, elements: list, path: str):
    """Vertices and triangulated faces of an ASCII PLY body already checked by ``_check_ply_ascii``."""
    tok = _decode_text(body, path, "ply").split()
    pos, verts, counts, corners = 0, None, [], []
    for name, count, props in elements:
        names = [p[0] for p in props]
        if name == "vertex" and not all(c in names for c in "xyz"):
            raise InputError(f"{path}: the PLY vertex element has no x, y, z properties")
        if all(len(p) == 2 for p in props):  # fixed-size records: one slice
            block = tok[pos:pos + count * len(props)]
            pos += count * len(props)
            if name == "vertex":
                try:
                    a = np.array(block, dtype=np.float64).reshape(count, len(props))
                except ValueError:
                    raise InputError(f"{path}: a PLY vertex record holds a value that is not a number") from None
                verts = a[:, [names.index(c) for c in "xyz"]]
            continue
        rows = []
        for _ in range(count):
            row = {}
            for p in props:
                if len(p) == 3:
                    n = int(tok[pos])
                    if name == "face" and p[0] in _PLY_FACE_LISTS:
                        if n < 3:
                            raise InputError(f"{path}: a PLY face has {n} vertices; a face needs at least 3")
                        counts.append(n)
                        corners.append(tok[pos + 1:pos + 1 + n])
                    pos += 1 + n
                else:
                    row[p[0]] = tok[pos]
                    pos += 1
            if name == "vertex":
                rows.append([row[c] for c in "xyz"])
        if name == "vertex":
            try:
                verts = np.array(rows, dtype=np.float64).reshape(count, 3)
            except ValueError:
                raise InputError(f"{path}: a PLY vertex record holds a value that is not a number") from None
    if verts is None:
        raise InputError(f"{path}: could not read the PLY vertex element")
    if not counts:
        return verts, np.zeros((0, 3), dtype=np.int64)
    try:
        k = np.array([c for cs in corners for c in cs], dtype=np.int64)
    except ValueError:
        raise InputError(f"{path}: a PLY face holds a vertex index that is not an integer") from None
    if k.min() < 0 or k.max() >= len(verts):
        raise InputError(f"{path}: PLY face indices must lie in [0, {len(verts)}), found {k.min()}..{k.max()}")
    return verts, _triangulate(k, np.asarray(counts, dtype=np.int64))


def _check_ply_ascii(body: bytes, elements: list, path: str) -> None:
    """Walk an ASCII PLY body token by token against the header: every declared record must be there, whole,
    and nothing may follow the last one (trimesh's reader stops quietly at the end of a short file, and reads
    only the declared records of a long one, so a cut or mis-declared file would load as a smaller mesh)."""
    tok = _decode_text(body, path, "ply").split()
    pos = 0
    for name, count, props in elements:
        lists = [k for k, p in enumerate(props) if len(p) == 3]
        if not lists:  # fixed-size records: one slice
            need = count * len(props)
            if pos + need > len(tok):
                done = (len(tok) - pos) // max(1, len(props))
                _truncated(path, name, count, done)
            pos += need
            continue
        if len(lists) == 1 and count:  # the usual face element: try records of one length first
            k = lists[0]
            first = tok[pos + k] if pos + k < len(tok) else None
            n0 = int(first) if first is not None and first.isdigit() else -1
            length = len(props) + n0
            if n0 >= 0 and pos + count * length <= len(tok) and all(
                    t == first for t in tok[pos + k:pos + count * length:length]):
                pos += count * length
                continue
        for done in range(count):  # records of several lengths (or a short file): one at a time
            for p in props:
                if pos >= len(tok):
                    _truncated(path, name, count, done)
                if len(p) == 3:
                    try:
                        n = int(tok[pos])
                    except ValueError:
                        raise InputError(f"{path}: PLY element {name!r}, record {done}: list length "
                                         f"{tok[pos]!r} is not a number") from None
                    if n < 0:
                        raise InputError(f"{path}: PLY element {name!r}, record {done}: negative list length {n}")
                    pos += n
                pos += 1
            if pos > len(tok):
                _truncated(path, name, count, done)
    if pos < len(tok):
        raise InputError(f"{path}: {len(tok) - pos} values follow the last record the PLY header declares "
                         f"({', '.join(f'{c} {n}' for n, c, _ in elements)}): the header's counts are wrong or "
                         "the file is damaged")


def _truncated(path: str, name: str, count: int, done: int):
    raise InputError(f"{path}: the PLY header declares {count} {name} records but the file ends after {done} of "
                     "them: it is truncated or damaged")


def _ply_binary(data: bytes, off: int, elements: list, endian: str, path: str):
    """Vertices and triangulated faces of a binary PLY file, element by element."""
    verts, counts, corners = None, [], []
    for name, count, props in elements:
        if all(len(p) == 2 for p in props):  # fixed-size records
            dt = np.dtype([(p[0], endian + _PLY_TYPES[p[1]]) for p in props])
            if off + count * dt.itemsize > len(data):
                raise InputError(f"{path}: PLY element {name!r} runs past the end of the file (truncated or corrupt)")
            rec = np.frombuffer(data, dtype=dt, count=count, offset=off)
            off += count * dt.itemsize
            if name == "vertex":
                if not all(c in dt.names for c in "xyz"):
                    raise InputError(f"{path}: the PLY vertex element has no x, y, z properties")
                verts = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)
            continue
        for _ in range(count):
            for p in props:
                if len(p) == 2:
                    off += np.dtype(_PLY_TYPES[p[1]]).itemsize
                    continue
                cdt, idt = np.dtype(endian + _PLY_TYPES[p[1]]), np.dtype(endian + _PLY_TYPES[p[2]])
                if off + cdt.itemsize > len(data):
                    raise InputError(f"{path}: PLY element {name!r} runs past the end of the file (truncated or corrupt)")
                n = int(np.frombuffer(data, dtype=cdt, count=1, offset=off)[0])
                off += cdt.itemsize
                if n < 0 or off + n * idt.itemsize > len(data):
                    raise InputError(f"{path}: PLY element {name!r} runs past the end of the file (truncated or corrupt)")
                if name == "face" and p[0] in _PLY_FACE_LISTS:
                    if n < 3:
                        raise InputError(f"{path}: a PLY face has {n} vertices; a face needs at least 3")
                    counts.append(n)
                    corners.append(np.frombuffer(data, dtype=idt, count=n, offset=off))
                off += n * idt.itemsize
    if verts is None:
        raise InputError(f"{path}: could not read the PLY vertex element")
    if not counts:
        return verts, np.zeros((0, 3), dtype=np.int64)
    k = np.concatenate(corners).astype(np.int64)
    if k.min() < 0 or k.max() >= len(verts):
        raise InputError(f"{path}: PLY face indices must lie in [0, {len(verts)}), found {k.min()}..{k.max()}")
    return verts, _triangulate(k, np.asarray(counts, dtype=np.int64))


# --- STL ------------------------------------------------------------------------------------------------------

def _read_stl(data: bytes, path: str):
    if not data.lstrip()[:5].lower() == b"solid":
        # binary STL: 80-byte header, uint32 count, 50 bytes per triangle
        if len(data) < 84:
            raise InputError(f"{path} is not a mesh file: too short for a binary STL ({len(data)} bytes)")
        count = int(np.frombuffer(data[80:84], dtype="<u4")[0])
        if 84 + 50 * count > len(data):
            raise InputError(f"{path} is not a valid binary STL: it declares {count} triangles "
                             f"({84 + 50 * count} bytes) but has {len(data)} bytes")
    v, f = _trimesh_arrays(data, "stl", path)
    if len(v) != 3 * len(f):
        raise InputError(f"{path}: expected three corners per STL triangle, read {len(v)} for {len(f)}")
    return v, f


# --- other formats --------------------------------------------------------------------------------------------

def _read_other(data: bytes, kind: str, path: str):
    if kind not in _member_kinds():
        raise InputError(f"{path}: unsupported mesh format {('.' + kind) if kind else '(no suffix)'}; "
                         f"use {_formats_message()}")
    return _trimesh_arrays(data, kind, path)


def _trimesh_arrays(data: bytes, kind: str, path: str):
    """Vertices and faces of the file's bytes as trimesh reads them with ``process=False`` (no merging, no
    reordering)."""
    import io

    import trimesh

    try:
        tm = trimesh.load(io.BytesIO(data), file_type=kind, process=False, force="mesh")
    except ImportError:
        # trimesh reaches for an optional text-encoding detector when a file is not UTF-8: it is not text
        raise InputError(f"{path} is not a mesh file: it is not text that the {kind.upper()} reader understands") from None
    except Exception as e:  # trimesh raises many types for bad or unknown files
        raise InputError(f"{path} is not a mesh file that the {kind.upper() or 'trimesh'} reader understands "
                         f"({type(e).__name__}: {e})") from None
    faces = getattr(tm, "faces", None)
    verts = getattr(tm, "vertices", None)
    if faces is None or verts is None or len(faces) == 0:
        raise InputError(f"mesh file {path} has no triangle faces: NeuroGF needs a triangle surface")
    v = np.asarray(verts, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    return v, f
