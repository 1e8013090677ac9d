"""One run's work spread over Ray workers, on this machine or a cluster (``train.workers``).

Ray is the ``cluster`` extra; nothing here imports it until workers are asked for.
"""

from __future__ import annotations

import importlib.util
import socket

EXTRA = "cluster"  # the extra that installs Ray: pip install 'mrta_rl[cluster]'
PROBE_S = 3.0  # how long a cluster's address may take to accept a connection


def ray_installed() -> bool:
    """Whether Ray is installed (the ``cluster`` extra), without importing it."""
    return importlib.util.find_spec("ray") is not None


def unreachable(address: str, timeout_s: float = PROBE_S) -> str | None:
    """Why no Ray cluster answers at ``address`` (``train.ray_address``), or None if one may.

    ``ray.init`` retries an address that does not answer for minutes; a connection to its
    port, tried here for ``timeout_s``, tells at once. ``auto`` is the address Ray itself finds
    (``ray start`` records it); ``ray://host:port`` (Ray client) and ``host:port`` are probed
    as they are.

    Args:
        address: The address to join.
        timeout_s: Seconds to wait for the connection.
    """
    target = address.removeprefix("ray://")
    if target == "auto":
        try:  # Ray's own lookup, a private function: without it, ray.init finds the address
            from ray._private.services import (  # noqa: PLC0415
                canonicalize_bootstrap_address_or_die,
            )
        except ImportError:
            return None
        try:
            target = canonicalize_bootstrap_address_or_die("auto")
        except ConnectionError:
            return "no running Ray instance found on this machine (start one with ray start --head)"
    host, _, port = target.rpartition(":")
    if not host or not port.isdigit():
        return "not an address of the form host:port, ray://host:port or auto"
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            return None
    except OSError as err:
        return f"nothing answers at {target} ({err.strerror or type(err).__name__})"
