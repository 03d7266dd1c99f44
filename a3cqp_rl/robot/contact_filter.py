"""An exact pre-filter of a tool's collision pairs with boxes, as MuJoCo's contact filter callback (in C).

Why: in the peg-in-hole scene MuJoCo's collision pass is most of a control period in contact. The peg (a 32-sided
prism) sits in a bore made of 32 boxes, and MuJoCo's midphase, whose bounding boxes of a round peg reach past its
circle, passes most of them to the narrow phase (GJK) at every step. `contact_filter.c` drops a tool-box pair when the
tool, bounded by a cylinder, lies farther than the pair's margin and gaps plus 10 µm from the box: by a plane normal
to one of the box's axes, or, for the part of the cylinder inside one of the box's slabs, by a bound along another
of its axes (a tilted peg whose end reaches a box's slab above the box's top). MuJoCo makes no contact of such a
pair, so every contact and every number after it stays as it was (tests/test_contact_filter.py: bit for bit, and
MuJoCo's own distance of every pair dropped above the slack).

MuJoCo has one contact filter per process, which replaces its contype/conaffinity test for every model; the C
callback applies that test first, so unregistered models collide as without it. `attach` installs the callback on
first use unless another one is set (then it warns once and filters nothing). `A3CQP_NATIVE_CONTACT=0` switches it
off; a library not built at install time logs one warning and nothing is filtered. A model with MuJoCo's contact
override on at registration is not registered (its o_margin would replace the margins the test reads); switching the
override on later is not followed.
"""

from __future__ import annotations

import ctypes
import logging
import threading
import weakref
from pathlib import Path

import mujoco
import numpy as np

from a3cqp_rl.native_build import LazyLibrary

__all__ = ["attach", "Registration", "SLACK", "bounding_cylinder"]

SOURCE = Path(__file__).with_name("native") / "contact_filter.c"
SLACK = 1e-5
"""Distance [m] a pair must be apart beyond its margin and gaps to be dropped: well above MuJoCo's collision
tolerance (ccd_tolerance 1e-6), well below the bore's 0.25 mm clearance."""

_log = logging.getLogger(__name__)
_FIELDS = ("m", "d", "size", "margin", "gap", "xpos", "xmat", "role", "cylinder")
_lock = threading.Lock()
_state: dict = {}  # "callback": the installed ctypes function, "foreign": warned about another filter


class _Entry(ctypes.Structure):
    """cf_entry of contact_filter.c."""

    _fields_ = [*((name, ctypes.c_void_p) for name in _FIELDS), ("slack", ctypes.c_double),
                ("tested", ctypes.c_int64), ("dropped", ctypes.c_int64), ("dropped_slab", ctypes.c_int64)]


def _bind(path: Path) -> ctypes.CDLL:
    lib = ctypes.CDLL(str(path))
    lib.cf_set_offsets.argtypes = [ctypes.c_int64, ctypes.c_int64]
    lib.cf_set_offsets.restype = None
    lib.cf_register.argtypes = [ctypes.c_void_p]
    lib.cf_register.restype = ctypes.c_int64
    lib.cf_unregister.argtypes = [ctypes.c_int64]
    lib.cf_unregister.restype = None
    lib.cf_counts.argtypes = [ctypes.c_int64, ctypes.c_void_p]
    lib.cf_counts.restype = None
    return lib


_library = LazyLibrary(SOURCE, "A3CQP_NATIVE_CONTACT", _bind, _log, "a3cqp_rl.robot: native contact pre-filter",
                       "MuJoCo's collision without it")


def _addr(a: np.ndarray) -> int:
    return a.__array_interface__["data"][0]


def _pointer_offset(m: mujoco.MjModel, array: np.ndarray) -> int:
    """Byte offset in the mjModel struct of the field that points to `array` (found once: one layout per build).

    Reads the struct from its start in growing spans (4, 8, 16 kB) and stops at the first span that holds the
    pointer, so that it reads no farther past the field than needed (the geom fields sit ~2.4 kB in, MuJoCo 4.0)."""
    for size in (1 << 12, 1 << 13, 1 << 14):
        words = np.frombuffer(ctypes.string_at(m._address, size), dtype=np.uint64)
        hits = np.flatnonzero(words == _addr(array))
        if len(hits) > 1:
            raise RuntimeError(f"the pointer to a geom array occurs {len(hits)} times in mjModel's first {size} bytes")
        if len(hits) == 1:
            return int(hits[0]) * 8
    raise RuntimeError("the pointer to a geom array is not in mjModel's first 16 kB")


def _install(lib: ctypes.CDLL, m: mujoco.MjModel) -> bool:
    """Install the callback once per process (False: another filter is set, or mjModel's layout is not found)."""
    if "callback" in _state:  # (None: the layout was not found)
        return _state["callback"] is not None and mujoco.get_mjcb_contactfilter() is _state["callback"]
    if mujoco.get_mjcb_contactfilter() is not None:
        if "foreign" not in _state:
            _log.warning("a MuJoCo contact filter is already set; the Panda's contact pre-filter stays off")
            _state["foreign"] = True
        return False
    contype, conaffinity = _pointer_offset(m, m.geom_contype), _pointer_offset(m, m.geom_conaffinity)
    if conaffinity != contype + 8:  # adjacent fields of mjModel in every MuJoCo release
        raise RuntimeError(f"mjModel's geom_contype / geom_conaffinity at offsets {contype} / {conaffinity}")
    lib.cf_set_offsets(contype, conaffinity)
    callback = ctypes.cast(lib.cf_filter, ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p,
                                                           ctypes.c_int, ctypes.c_int))
    mujoco.set_mjcb_contactfilter(callback)
    _state["callback"] = callback
    return True


def bounding_cylinder(m: mujoco.MjModel, geom: int) -> tuple[int, float, float]:
    """(axis, half-length, radius) [m] of the smallest of the three cylinders along the mesh geom's own axes and
    about its origin that contain its vertices (a hair larger: 1e-9 relative)."""
    mesh = int(m.geom_dataid[geom])
    start = int(m.mesh_vertadr[mesh])
    v = m.mesh_vert[start:start + int(m.mesh_vertnum[mesh])].astype(np.float64)
    best = None
    for axis in range(3):
        h = float(np.abs(v[:, axis]).max())
        rho = float(np.sqrt((np.delete(v, axis, axis=1) ** 2).sum(1)).max())
        if best is None or rho * rho * h < best[2] * best[2] * best[1]:
            best = (axis, h, rho)
    axis, h, rho = best
    return axis, h * (1 + 1e-9), rho * (1 + 1e-9)


def attach(m: mujoco.MjModel, d: mujoco.MjData, tools: np.ndarray, boxes: np.ndarray) -> Registration | None:
    """Register (m, d) with the pre-filter for the pairs of the mesh geoms `tools` and the box geoms `boxes`.

    Returns the Registration (it holds m and d until detached or collected; PandaSim's goes with the sim), or None
    when nothing is filtered (no library, another filter, MuJoCo's contact override, or every registration slot
    taken)."""
    lib = _library.get()
    tools, boxes = np.asarray(tools, dtype=np.intp), np.asarray(boxes, dtype=np.intp)
    if lib is None or not len(tools) or not len(boxes):
        return None
    if not (m.geom_type[tools] == mujoco.mjtGeom.mjGEOM_MESH).all():
        raise ValueError("contact pre-filter: the tool geoms must be meshes")
    if not (m.geom_type[boxes] == mujoco.mjtGeom.mjGEOM_BOX).all():
        raise ValueError("contact pre-filter: the box geoms must be boxes")
    if m.opt.enableflags & int(mujoco.mjtEnableBit.mjENBL_OVERRIDE):
        _log.warning("contact pre-filter off for a model with MuJoCo's contact override (its o_margin replaces the "
                     "geoms' margins, which the filter reads)")
        return None
    with _lock:
        try:
            if not _install(lib, m):
                return None
        except RuntimeError as exc:
            _log.warning("contact pre-filter off: %s", exc)
            _state["callback"] = None
            return None
        role, cylinder = np.zeros(m.ngeom, dtype=np.int8), np.zeros((m.ngeom, 3))
        role[boxes] = 2
        role[tools] = 1
        cylinder[tools] = [bounding_cylinder(m, g) for g in tools]
        arrays = (m.geom_size, m.geom_margin, m.geom_gap, d.geom_xpos, d.geom_xmat, role, cylinder)
        entry = _Entry(m._address, d._address, *(_addr(a) for a in arrays), SLACK, 0, 0, 0)
        slot = int(lib.cf_register(ctypes.byref(entry)))
    if slot < 0:
        _log.warning("contact pre-filter: every registration slot is taken; this simulation runs without it")
        return None
    return Registration(lib, slot, (m, d, role, cylinder))


class Registration:
    """One (model, data) registered with the pre-filter: its counts, and `detach()`.

    The filter finds a registration by the addresses of its model and data, so it holds both: a registration
    dropped without `detach()` while they were freed would match a model and data allocated later at the same
    addresses, and be read with the old one's arrays. It detaches itself when collected."""

    def __init__(self, lib: ctypes.CDLL, slot: int, keep: tuple) -> None:
        self._lib, self._slot, self._held = lib, slot, keep  # the model, data and arrays the slot reads until detach()
        self._out = np.zeros(3, dtype=np.int64)
        self._unregister = weakref.finalize(self, lib.cf_unregister, slot)

    @property
    def role(self) -> np.ndarray | None:
        """Each geom's role [ngeom] (0 other, 1 tool, 2 box), read by the filter in place (zeroed, it drops nothing);
        None after `detach()`."""
        return None if self._held is None else self._held[2]

    def counts(self) -> tuple[int, int]:
        """(tool-box pairs seen, pairs dropped) so far."""
        return self.counts_by_test()[:2]

    def counts_by_test(self) -> tuple[int, int, int]:
        """(tool-box pairs seen, pairs dropped, of those the ones the bound through a box's slab dropped) so far."""
        self._lib.cf_counts(self._slot, self._out.ctypes.data)
        return int(self._out[0]), int(self._out[1]), int(self._out[2])

    def detach(self) -> None:
        """Unregister (once); the filter then leaves this model's pairs to MuJoCo."""
        self._unregister()  # (a finalizer runs once)
        self._held = None
