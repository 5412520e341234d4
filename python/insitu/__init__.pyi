"""Type stubs of the insitu package (its extension module insitu._insitu)."""

from typing import Optional, Tuple, TypedDict

import numpy as np
import numpy.typing as npt

class PushReply(TypedDict):
    queue_depth: int
    """Steps waiting in the node's queue after this push."""
    dropped_by_push: int
    """Older steps this push displaced (the drop-oldest and latest-only policies)."""
    steps_received: int
    """Steps the node has received so far (all clients)."""
    epoch: int
    """This run of the node: a new value means it restarted (docs/guarantees.md)."""

class NodeStatus(TypedDict):
    queue_depth: int
    steps_received: int
    steps_generated: int
    steps_shipped: int
    dropped_queue: int
    dropped_outbox: int
    failed: int

class Error(Exception):
    """A call to the generator-node failed; the message says why."""

class UnreachableError(Error):
    """Nothing answers at the address, or the connection broke."""

class RefusedError(Error):
    """The node refused the call: a bad step (e.g. a brick outside the grid), a wrong token,
    shutting down, or (from flush) VDIs of this client's ranks that the viz-node refused."""

class TimeoutError(Error):
    """flush or close did not finish within its timeout."""

class Client:
    """A connection to one generator-node.

    ``Client(address, token=None)``: ``address`` is ``host:port`` or ``http://host:port``;
    ``token`` (default: the ``INSITU_TOKEN`` environment variable) is sent with every call.
    Raises UnreachableError when nothing answers, ValueError for a bad address or a token
    that would travel in clear text off loopback. Use as a context manager to close (and
    flush) on exit.
    """

    def __init__(self, address: str, token: Optional[str] = None) -> None: ...
    def push(
        self,
        step: int,
        field: npt.NDArray[np.float32 | np.float64 | np.uint8 | np.uint16 | np.int16],
        *,
        offset: Tuple[int, int, int] = (0, 0, 0),
        global_dims: Optional[Tuple[int, int, int]] = None,
        rank: int = 0,
        world_size: int = 1,
        spacing: Tuple[float, float, float] = (1.0, 1.0, 1.0),
        origin: Tuple[float, float, float] = (0.0, 0.0, 0.0),
        sim_time: float = 0.0,
    ) -> PushReply:
        """Pushes rank ``rank`` of ``world_size``'s brick of step ``step`` and returns once the
        node has queued it (the array may be changed then, not before).

        ``field``: shape ``(nz, ny, nx)``, C-contiguous, float32/float64/uint8/uint16/int16 in
        native byte order; sent without a copy. ``offset`` (x, y, z): the brick's first point in
        the whole grid; ``global_dims`` (x, y, z): the whole grid's points (default: offset +
        the brick's dims). Dims count points: where a neighbouring rank's brick follows along an
        axis, the brick repeats that neighbour's first plane. ``spacing`` (x, y, z): world units
        between points; ``origin``: the whole grid's first point; ``sim_time`` in the
        simulation's units.

        Raises TypeError (not an ndarray, a dtype the service does not take), ValueError (not
        3-D, not C-contiguous, negative offsets, non-finite spacing, a closed client, a brick
        inconsistent with its dims), RefusedError (the node refused the step: e.g. a brick
        outside the grid, rank ≥ world_size), UnreachableError.
        """
    def flush(self, timeout: Optional[float] = None) -> NodeStatus:
        """Waits until every step the node has received is generated and shipped (at most
        ``timeout`` seconds, default 600); the node's counters. Raises TimeoutError,
        RefusedError (the viz-node refused VDIs of this client's ranks since their last
        flush), UnreachableError, ValueError (closed)."""
    def status(self) -> NodeStatus:
        """The node's counters."""
    def close(self, timeout: Optional[float] = None) -> Optional[NodeStatus]:
        """Flushes, then closes (None when already closed). Later calls raise ValueError."""
    @property
    def closed(self) -> bool: ...
    @property
    def address(self) -> str: ...
    def __enter__(self) -> "Client": ...
    def __exit__(self, *exc: object) -> bool:
        """Closes (flushing). Leaving the block by an exception raises that exception alone: a
        close that fails then adds no second traceback."""

Field3 = npt.NDArray[np.float32 | np.float64 | np.uint8 | np.uint16 | np.int16]
"""A volume indexed [z, y, x]: shape (nz, ny, nx)."""

def render(
    volume: Field3,
    tf: Optional[str] = None,
    *,
    size: int = 512,
    angle: float = 0.0,
    elevation: float = 0.0,
    spacing: Tuple[float, float, float] = (1.0, 1.0, 1.0),
    origin: Tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> npt.NDArray[np.float32]:
    """Direct volume rendering (emission–absorption ray-casting, the reference of q) of
    ``volume`` from the default camera for its box, orbited by ``angle`` degrees about +y and
    raised by ``elevation`` (within ±89). ``tf``: transfer-function JSON text or a file
    (docs/conventions.md format); None: a ramp over the data's range. Returns an array of
    shape (size, size, 3), RGB in [0, 1]. Raises TypeError (dtype) or ValueError (shape,
    angles, size, a bad transfer function)."""

class Vdi:
    """A Volumetric Depth Image: r × r rays, each a depth-ordered list of supersegments."""

    def render(
        self, *, size: int = 512, angle: float = 0.0, elevation: float = 0.0
    ) -> npt.NDArray[np.float32]:
        """The VDI rendered from its generation camera orbited by ``angle`` (about +y) and
        raised by ``elevation`` degrees: an array (size, size, 3), RGB in [0, 1]."""
    def save(self, path: str, codec: str = "zstd") -> int:
        """Writes the VDI file (codec "zstd", "bzip2" or "none"), atomically; returns σ, its
        bytes. Raises ValueError naming the file when it cannot be written."""
    @staticmethod
    def load(path: str) -> "Vdi":
        """Reads a VDI file; ValueError naming the file when it is not one (or is damaged)."""
    @property
    def resolution(self) -> int: ...
    @property
    def gamma(self) -> float: ...
    @property
    def supersegments(self) -> int: ...

def generate(
    volume: Field3,
    tf: Optional[str] = None,
    *,
    r: int = 256,
    gamma: float = 0.013,
    precision: str = "8",
    spacing: Tuple[float, float, float] = (1.0, 1.0, 1.0),
    origin: Tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> Vdi:
    """The VDI of ``volume`` at P_M = (r, γ, precision) from the default camera for its box;
    ``precision`` (colour bits "4"–"16", or "f32" for lossless floats) is what ``Vdi.save``
    writes it at."""

class Evaluation(TypedDict):
    r: int
    gamma: float
    codec: str
    precision: str
    sigma_bytes: int
    """σ: bytes of the compressed VDI file."""
    supersegments: int
    tau_s: float
    """τ: seconds of VDI generation."""
    tau_compress_s: float
    tau_render_s: float
    """Mean seconds to render the VDI at one view."""
    q_db: float
    """q: PSNR of the mean MSE over the views against direct rendering, dB."""
    views: list[Tuple[float, float]]
    """(angle in degrees, PSNR in dB) per view."""

def evaluate(
    volume: Field3,
    tf: Optional[str] = None,
    *,
    r: int = 256,
    gamma: float = 0.013,
    codec: str = "zstd",
    size: int = 256,
    views: Optional[list[float]] = None,
    spacing: Tuple[float, float, float] = (1.0, 1.0, 1.0),
    origin: Tuple[float, float, float] = (0.0, 0.0, 0.0),
    precision: str = "8",
) -> Evaluation:
    """σ, τ and q of P_M = (r, γ, precision) on ``volume`` (the paper's Alg. 1, lines
    11–18): the VDI generated, written at ``precision`` (colour bits "4"–"16", or "f32"),
    compressed with ``codec``, decoded, rendered at the test views (orbit angles, degrees;
    default 0 to 60 by 10) and compared with direct rendering at ``size`` × ``size``."""

class Recording:
    """A viz-node's recording (its directory), read-only: a running viz-node may go on writing.
    Raises ValueError naming the directory when it holds no readable index."""

    def __init__(self, path: str) -> None: ...
    @property
    def steps(self) -> list[dict]:
        """Every stored step in order: step, world_size, ranks, missing, error, vdi (its file),
        r, gamma, pm_version, sigma_bytes, supersegments, tau_s, q_db (None until scored);
        sim_time for a step of one rank. A step of several ranks is the composed one."""
    def vdi(self, step: int) -> Vdi:
        """The step's VDI (composed over its ranks). KeyError for a step not stored,
        ValueError for one without a VDI (partial, refused) or a damaged file."""
    def image(
        self, step: int, *, size: int = 512, angle: float = 0.0, elevation: float = 0.0
    ) -> npt.NDArray[np.float32]:
        """The step's picture from its generation camera orbited by ``angle`` and raised by
        ``elevation`` degrees: an array (size, size, 3), RGB in [0, 1]."""
    def __len__(self) -> int: ...
