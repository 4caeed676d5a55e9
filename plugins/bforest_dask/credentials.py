"""TLS credentials for a Dask cluster that only its owner can use (docs/dask.md).

``python -m bforest_dask.credentials DIR`` writes ``DIR/ca.pem`` (the certificate every member of
the cluster trusts), ``DIR/cert.pem`` and ``DIR/key.pem`` (the one certificate and private key the
scheduler, the workers and the client present), made fresh with distributed's
``Security.temporary()`` and readable by the owner only. Start the scheduler and the workers with
them (``dask scheduler --tls-ca-file DIR/ca.pem --tls-cert DIR/cert.pem --tls-key DIR/key.pem``,
the same for ``dask worker``, or dask-jobqueue's ``security=``) and name them in the run's or the
stand's ``[executor]`` (``tls_ca_file``, ``tls_cert``, ``tls_key``): a client without them cannot
connect, and the traffic is encrypted. An existing credential file is never replaced.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

#: the files :func:`write_credentials` writes, by the role each plays
FILES = {"ca": "ca.pem", "cert": "cert.pem", "key": "key.pem"}


def write_credentials(folder, security=None) -> dict[str, Path]:
    """Write fresh TLS credentials (or those of ``security``, a distributed ``Security`` made by
    ``Security.temporary()``) into ``folder`` (created, mode 0700; each file 0600).

    Returns
    -------
    dict
        ``{"ca": path, "cert": path, "key": path}``.

    Raises
    ------
    FileExistsError
        When one of the files exists (credentials in use are never replaced).
    """
    from distributed.security import Security

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    os.chmod(folder, 0o700)
    paths = {k: folder / v for k, v in FILES.items()}
    for p in paths.values():
        if p.exists():
            raise FileExistsError(f"{p}: exists; credentials in use are never replaced (choose another folder)")
    sec = Security.temporary() if security is None else security
    texts = {"ca": sec.tls_ca_file, "cert": sec.tls_client_cert, "key": sec.tls_client_key}
    for k, p in paths.items():
        fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w", encoding="ascii") as fh:
            fh.write(texts[k])
    return paths


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1 or argv[0].startswith("-"):
        print("usage: python -m bforest_dask.credentials DIR", file=sys.stderr)
        return 2
    try:
        paths = write_credentials(argv[0])
    except (FileExistsError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for k, p in paths.items():
        print(f"{k}: {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
