"""`csr serve`: the HTTP API (contract section 4). Migrations run at start.

No CSR_DATABASE_URL: the embedded default (SQLite file under CSR_DATA_DIR, or ``--data-dir``, in-process
jobs): ``csr serve --data-dir data/demo/service`` serves what ``csr demo`` made once more.
CSR_DATABASE_URL=postgresql+psycopg://... and CSR_REDIS_URL=redis://...: the distributed API.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="start the HTTP API (embedded default unless CSR_DATABASE_URL is set)")
    p.add_argument("--host", default="127.0.0.1", help="bind address (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    p.add_argument("--no-access-log", action="store_true", help="do not log every request")
    p.add_argument(
        "--data-dir",
        type=Path,
        default=None,
        help="the embedded deployment's data dir (sets CSR_DATA_DIR; default ./data); "
        "data/demo/service holds what `csr demo` made",
    )
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    import uvicorn

    from services.api.app import create_app
    from services.settings import get_settings

    if args.data_dir is not None:
        os.environ["CSR_DATA_DIR"] = str(args.data_dir.resolve())
    app = create_app(get_settings())
    uvicorn.run(
        app,
        host=args.host,
        port=args.port,
        access_log=not args.no_access_log,
        log_config=None,
        timeout_graceful_shutdown=10,
    )
    return 0
