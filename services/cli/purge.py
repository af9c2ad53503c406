"""`csr purge --vehicle ID [--dry-run]`: erase a vehicle's trips and everything keyed by them in one
transaction, and queue the re-merge of the tiles they touched (``services.erasure``); the running
deployment's runners make the new map versions without them. ``--dry-run`` lists what would go.
Configured like `csr serve` (CSR_DATABASE_URL / CSR_DATA_DIR). A second purge finds nothing."""

from __future__ import annotations

import argparse
import sys
import time


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("purge", help="erase a vehicle's trips and re-merge the tiles they touched")
    p.add_argument("--vehicle", required=True, metavar="ID", help="the vehicle_id whose data goes")
    p.add_argument("--dry-run", action="store_true", help="list what would be erased; change nothing")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from services.db.engine import make_engine, make_session_factory, migrate
    from services.erasure import erase_vehicle, plan_vehicle_erasure
    from services.settings import get_settings

    settings = get_settings()
    engine = make_engine(settings.sqlalchemy_url)
    try:
        migrate(engine)
        session_factory = make_session_factory(engine)
        if args.dry_run:
            with session_factory.begin() as session:
                plan = plan_vehicle_erasure(session, vehicle_id=args.vehicle)
            for pk in plan.trip_pks:
                print(f"trip {pk}")
            for z, x, y in plan.tiles:
                print(f"tile {z}/{x}/{y}")
            print(
                f"csr purge --dry-run: vehicle {args.vehicle}: {len(plan.trip_pks)} trip(s) and "
                f"{len(plan.tiles)} tile(s) to re-merge would be erased; nothing changed"
            )
            return 0
        with session_factory.begin() as session:
            plan = plan_vehicle_erasure(session, vehicle_id=args.vehicle)
            with tqdm(
                total=len(plan.trip_pks), desc=f"purge {args.vehicle}", unit="trip", file=sys.stderr
            ) as bar:
                result = erase_vehicle(session, plan=plan, progress=bar.update)
            if settings.test_purge_delay_s:
                time.sleep(settings.test_purge_delay_s)
        if not result.trips:
            print(f"csr purge: vehicle {args.vehicle} has no trips: nothing to erase")
            return 0
        print(
            f"csr purge: vehicle {args.vehicle}: erased {result.trips} trip(s) ({result.match_pairs} match "
            f"pair(s), {result.jobs} job(s)); {result.versions_rewritten} tile version(s) no longer name them; "
            f"{len(result.merge_jobs)} merge job(s) queued for {len(result.tiles)} tile(s)"
        )
        return 0
    finally:
        engine.dispose()
