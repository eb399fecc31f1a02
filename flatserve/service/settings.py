"""Service settings (pydantic-settings, environment prefix ``FLATSERVE_``).

Every option can be given as an environment variable, e.g.
``FLATSERVE_DATA_DIR=/var/lib/flatserve FLATSERVE_API_KEY=... flatserve serve``.
"""
from __future__ import annotations

import ipaddress
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

#: Field names: a letter or digit, then up to 63 letters, digits, ``_ . -``.
#: No ``/``, no leading dot: a name can never become a path.
FIELD_NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"

MiB = 1 << 20


class Settings(BaseSettings):
    """Configuration of one flatserve server process."""

    model_config = SettingsConfigDict(
        env_prefix="FLATSERVE_", extra="ignore", use_attribute_docstrings=True)

    host: str = Field("127.0.0.1")
    """Interface to bind."""
    port: int = Field(8000, ge=0, le=65535)
    """Port to bind (0: a free port chosen by the system)."""
    data_dir: Path = Field(Path("data"))
    """SQLite database and snapshots live here."""
    workers: int = Field(8, ge=1, le=256)
    """Threads of each replica process running CPU-heavy handlers (upload, query, math) in parallel
    (see processes for more processes)."""
    blas_threads: int = Field(1, ge=0, le=256)
    """Threads of NumPy's BLAS in the server process (0: leave as is). The service's NumPy products
    are thin; a threaded BLAS only spins on them."""
    api_key: SecretStr | None = Field(None)
    """Read-write API key."""
    read_only_key: SecretStr | None = Field(None)
    """Read-only API key (queries, GETs)."""
    allowed_hosts: Annotated[list[str], NoDecode] = Field(default_factory=list)
    """Host header values accepted (names or addresses, without the port; comma-separated; '*'
    any), others get 421: a page of another site that makes its name resolve to this server
    (DNS rebinding) is refused. Empty (the default): the bound address and the localhost names
    (localhost, 127.0.0.1, ::1); any when bound to a wildcard address (0.0.0.0, ::), which
    needs api_key. Set it to the names clients use behind a proxy."""
    cors_origins: Annotated[list[str], NoDecode] = Field(default_factory=list)
    """Origins (scheme://host[:port], comma-separated; '*' any) whose web pages may call this
    server from a browser (CORS). Empty (the default): no CORS, and requests whose Origin header
    names another origin are refused (403)."""
    max_body_bytes: int = Field(512 * MiB, ge=1)
    """Largest accepted request body (413)."""
    max_json_bytes: int = Field(8 * MiB, ge=1)
    """Largest JSON body (413): parsing JSON holds the interpreter for its whole length, so bulk
    arrays travel as .npy / .npz (up to max_body_bytes)."""
    max_batch_rows: int = Field(1_000_000, ge=1)
    """Most rows in one upload or query (413)."""
    max_json_answer_bytes: int = Field(64 * MiB, ge=1)
    """Largest JSON answer, estimated before any work is done (413 naming the estimate): writing
    JSON holds the interpreter for its whole length, so bulk answers travel as .npy (a query
    with Accept: application/x-npy)."""
    max_answer_bytes: int = Field(512 * MiB, ge=1)
    """Largest binary answer (.npy / .npz of a query, a rendered .npy frame), estimated before
    any work is done (413): split the batch."""
    max_fields: int = Field(256, ge=1)
    """Most fields on this server (409)."""
    max_pending_samples: int = Field(2_000_000, ge=1)
    """Most accepted samples of one field waiting for their insert (uploads with wait=false);
    beyond it uploads get 429 with Retry-After."""
    max_simplices: int = Field(50_000_000, ge=1)
    """Most cells of one field's triangulation: an upload expected to pass it is refused (413) with
    the estimate (high-dimensional fields grow fast)."""
    min_field_samples: int = Field(1000, ge=0)
    """Fewest samples a new field must be able to hold under max_simplices: a create of a kind
    whose estimate (max_simplices / (cells per sample of its triangulation dimension x the
    charts holding each sample)) is lower is refused (413) naming both settings (0: never)."""
    max_import_batches: int = Field(100_000, ge=1)
    """Most batches one import file (POST /v1/fields/{name}/import) may list (413): an import
    checks them all, then stores them one by one within its one request."""
    max_atlas_samples: int = Field(100_000, ge=1)
    """Most flats given to build a data-driven atlas (`basis: {"kind": "atlas", "atlas":
    "samples"}`) when a field is created (413)."""
    insert_slice_rows: int = Field(20_000, ge=1)
    """Batches acknowledged before indexing (wait=false) are inserted this many samples at a time,
    so queries get in between (they see such a batch in part until indexed_batch reaches it);
    wait=true batches are inserted whole before their acknowledgement."""
    shard_threads: int | None = Field(None, ge=1, le=256)
    """Threads of each replica process that run one field's shards (an atlas field's charts)
    at once: inserts, queries, snapshots and restores (unset: the cores it may run on). Answers
    do not depend on it."""
    restore_threads: int = Field(4, ge=1, le=64)
    """Fields restored at once on start (each is ready as soon as it is loaded)."""
    snapshot_every: int = Field(100_000, ge=0)
    """Write a snapshot in the background after this many new samples (0: never)."""
    header_timeout: float = Field(10.0, gt=0)
    """Seconds to receive a request's header block, from the connection's opening or the request's
    first byte; then the connection is closed (408 if part of a request had arrived)."""
    body_timeout: float = Field(60.0, gt=0)
    """Seconds to receive a request's body after its headers, plus one second per body_min_rate
    bytes received; then 408 and the connection is closed."""
    body_min_rate: int = Field(64 * 1024, ge=1)
    """Bytes per second that always get a body through (see body_timeout): a body dripping slower
    is cut off after about body_timeout seconds."""
    keepalive_timeout: float = Field(5.0, gt=0)
    """Seconds an idle keep-alive connection stays open."""
    max_connections: int = Field(1000, ge=0)
    """Open connections admitted; beyond it a new connection's requests get 503 (and one that sends
    nothing is closed after a second) while admitted ones keep working. Each holds a file
    descriptor: on start the open-files limit (ulimit -n) is raised toward its hard limit if
    needed, else the cap is lowered to fit, with a warning (0: as many as the limit allows)."""
    database_url: str | None = Field(None)
    """Where the shared batch log lives: unset for SQLite in data_dir (one machine), or
    postgresql://user:pass@host/db for replicas on several machines."""
    ray: str | None = Field(None)
    """Cluster mode: the address of a Ray cluster (host:port of its head, or 'auto') holding the
    fields' shards in actors on its nodes; this server is then a stateless front (routes, fans
    out, blends). The log every shard follows is database_url's PostgreSQL, or, unset, the SQLite
    database of data_dir for a one-machine cluster (every Ray node on this machine: the shards
    read the directory this server holds; a node elsewhere is refused at start, and one that
    joins later is given no shard or tile: they are kept on the nodes of this server's
    address). Needs the cluster extra (pip install 'flatserve[cluster]')."""
    ray_shards: int = Field(4, ge=1, le=1024)
    """Cluster mode: shard groups per field (an atlas field's charts divided among them; a one-chart
    field is one group). Each group is an actor per copy."""
    ray_shard_memory: int = Field(1 << 30, ge=1 << 20)
    """Cluster mode: bytes of a node's Ray memory resource each shard actor reserves (a node holds
    shards up to its budget: start a node with ray start --memory BYTES)."""
    ray_tile_samples: int = Field(100_000, ge=1_000)
    """Cluster mode: a one-chart field made with tiles "auto" gets a tile (a Ray actor of its own)
    per this many samples, up to 64; between two cuts a tile holds up to about twice as many
    (a tile of 200,000 of the paper's rays, its halo included, is 1.1 GiB resident:
    docs/scaling.md; the default ray_shard_memory is 1 GiB)."""
    ray_namespace: str = Field("flatserve", min_length=1, max_length=64)
    """Cluster mode: the Ray namespace of the shard actors (fronts of one deployment share it)."""
    processes: int = Field(1, ge=1, le=256)
    """Replica processes serving one port (SQLite backend: they share the data directory; each
    holds its own copy of every field's triangulation)."""
    accept_when_ready: bool = Field(False)
    """Take connections only once the stored fields are restored (the replicas of processes > 1
    always do, so a restarted one leaves its connections to a ready sibling). Behind a load
    balancer a restarting replica is then refused connections, which the balancer passes on,
    instead of answering 503 while it loads; a lone server's clients wait for it instead."""
    read_wait_timeout: float = Field(10.0, ge=0)
    """Seconds a read with min_position waits for this replica to apply that log position; then 503
    with Retry-After."""
    apply_wait_timeout: float = Field(60.0, gt=0)
    """Seconds a committed write (a wait=true upload, a create, a delete, a query with wait=true)
    waits for this replica to apply it; then 503 with Retry-After: the write is stored (an
    upload retried with the same Idempotency-Key gets its response)."""
    log_poll_interval: float = Field(0.005, gt=0, le=1.0)
    """Seconds between two checks for entries other processes appended to the log (SQLite: PRAGMA
    data_version; this process's own commits wake the follower at once)."""
    snapshot_lease_seconds: float = Field(300.0, gt=0)
    """A replica writing a snapshot holds a lease this long (renewed while it writes); a replica
    killed while writing blocks other writers until then."""
    lock_fd: int | None = Field(None, ge=0)
    """Internal (set by --processes for its children): an inherited open file that holds the data
    directory's lock for the whole replica group."""
    replica: int = Field(0, ge=0)
    """Internal (set by --processes for its children): this replica's index, the `replica`
    label of its metrics."""
    log_level: str = Field("info")
    """Least level logged: debug, info, warning, error."""
    log_format: Literal["text", "json"] = Field("text")
    """Log lines as text or as one JSON object a line (stderr)."""
    access_log: bool = Field(True)
    """One log line per request (flatserve.access): method, route, field, rows, status, ms,
    request id."""
    demo: bool = Field(False)
    """On start, create the bunny light-field demo field unless stored (background, with progress)
    and print the viewer URL (`make run` sets it)."""

    @field_validator("api_key", "read_only_key", mode="before")
    @classmethod
    def _empty_is_unset(cls, v):
        return None if v is None or (isinstance(v, str) and not v.strip()) else v

    @field_validator("allowed_hosts", "cors_origins", mode="before")
    @classmethod
    def _comma_list(cls, v):
        if isinstance(v, str):
            v = v.split(",")
        return [x.strip() for x in v if x and x.strip()] if v is not None else []

    @field_validator("cors_origins")
    @classmethod
    def _origins(cls, v: list[str]) -> list[str]:
        for o in v:
            if o != "*" and (not o.startswith(("http://", "https://")) or o.count("/") != 2):
                raise ValueError(f"cors_origins: {o!r} is not an origin: "
                                 "scheme://host[:port], no path (or '*')")
        return [o.lower() for o in v]

    @model_validator(mode="after")
    def _keys(self) -> "Settings":
        if self.read_only_key is not None and self.api_key is None:
            raise ValueError("read_only_key needs api_key (the read-write key) to be set too")
        if self.api_key is not None and self.read_only_key is not None:
            if self.api_key.get_secret_value() == self.read_only_key.get_secret_value():
                raise ValueError("api_key and read_only_key must differ")
        return self

    @property
    def auth_enabled(self) -> bool:
        return self.api_key is not None

    def bind_host(self) -> str:
        """The host actually bound: loopback only when no API key is set."""
        if self.auth_enabled or is_loopback(self.host):
            return self.host
        return "127.0.0.1"


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False
