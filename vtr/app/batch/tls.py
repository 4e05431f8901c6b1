"""TLS of a batch's cluster: temporary credentials for the local cluster, and the check that a ``tls://`` scheduler has
this client's certificates in Dask's configuration.

The local cluster listens on loopback only, with TLS and credentials made for the batch alone (``Security.temporary()``,
never written to disk): only the batch's own client and workers can connect. See the README's "Batches" section and
``docs/outputs.md``.
"""

from __future__ import annotations

from typing import Any

from ...errors import ConfigError


def check_scheduler_tls(address: str | None) -> None:
    """A ``tls://`` scheduler needs this client's certificates from Dask's configuration; ``ConfigError`` naming the
    settings when there are none (distributed would fail deep inside with a ``TypeError``)."""
    if address is None or not address.startswith("tls://"):
        return
    from distributed.security import Security  # Dask only for a remote scheduler

    if Security().get_connection_args("client").get("ssl_context") is None:
        raise ConfigError(
            f"--scheduler {address}: tls:// needs this client's TLS certificates in Dask's configuration "
            "(distributed.comm.tls.ca-file, distributed.comm.tls.client.cert and .key, e.g. in "
            "~/.config/dask/distributed.yaml or DASK_DISTRIBUTED__COMM__TLS__CA_FILE=...); none is set"
        )


def local_security() -> Any:
    """TLS with credentials made for this batch alone (a temporary CA-less key pair, never written to disk):
    a process without them cannot connect to the local scheduler or its workers."""
    try:
        from distributed.security import Security  # Dask only for the local cluster

        return Security.temporary()
    except ImportError as err:  # pragma: no cover - cryptography is a dependency
        raise ConfigError(f"the local Dask cluster needs the 'cryptography' package for TLS ({err})") from None
