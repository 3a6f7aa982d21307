"""A real PostgreSQL server for the archive's tests (no mocks): the installed server's ``initdb`` and ``pg_ctl``
in a private temporary folder, a free TCP port on 127.0.0.1 and its own unix socket folder.

* One server per test session **per xdist worker** (a session-scoped fixture: each worker process has its own
  server, folder and port), stopped at the end (``pg_ctl stop -m immediate``; nothing left running).
* ``initdb`` refuses to run as root: as root the server runs as the ``postgres`` user (``runuser``).
* Roles as a site sets them up (docs/archive.md): ``linarmpp_owner`` owns each test database and runs the
  migrations; ``linarmpp_app`` is the stations' role, with only the grants of
  ``app.archive.schema.grant_statements``. Both log in with a password over TCP (scram-sha-256), read from a
  password file only the user can read — never from a URL. The superuser connects without one (trust).
* When the server cannot be started the tests are skipped, but under ``CI=true`` they fail.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import shutil
import socket
import subprocess
import tempfile
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

PG_BIN_CANDIDATES = [Path(f"/usr/lib/postgresql/{v}/bin") for v in (17, 16, 15, 14, 13)]
OWNER, APP = "linarmpp_owner", "linarmpp_app"


def pg_bin() -> Path | None:
    env = os.environ.get("LINARMPP_PG_BIN")
    for d in ([Path(env)] if env else []) + PG_BIN_CANDIDATES:
        if (d / "initdb").is_file() and (d / "pg_ctl").is_file():
            return d
    found = shutil.which("initdb")
    return Path(found).parent if found else None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class Database:
    name: str
    server: PostgresServer

    def url(self, role: str = APP) -> str:
        return f"postgresql+psycopg://{role}@127.0.0.1:{self.server.port}/{self.name}"

    @property
    def admin_url(self) -> str:
        return f"postgresql+psycopg://postgres@127.0.0.1:{self.server.port}/{self.name}"

    def password_file(self, role: str = APP) -> str:
        return str(self.server.secrets / role)


class PostgresServer:
    def __init__(self) -> None:
        binary = pg_bin()
        if binary is None:
            raise RuntimeError("no PostgreSQL server binaries (initdb, pg_ctl) on this machine")
        self.bin = binary
        self.base = Path(tempfile.mkdtemp(prefix="linarmpp-pg-"))
        self.data = self.base / "data"
        self.sock = self.base / "sock"
        self.log = self.base / "server.log"
        self.secrets = Path(tempfile.mkdtemp(prefix="linarmpp-pg-secrets-"))  # the test user's, 0700
        self.port = 0
        self.running = False
        self._as_root = os.geteuid() == 0 if hasattr(os, "geteuid") else False
        self.sock.mkdir()
        if self._as_root:
            shutil.chown(self.base, "postgres", "postgres")
            shutil.chown(self.sock, "postgres", "postgres")
        self._run([str(self.bin / "initdb"), "-D", str(self.data), "-U", "postgres", "-A", "trust", "-E", "UTF8",
                   "--no-sync", "--no-instructions"])
        hba = ("local all all trust\n"
               "host all postgres 127.0.0.1/32 trust\n"
               "host all all 127.0.0.1/32 scram-sha-256\n")
        self._write_as_server(self.data / "pg_hba.conf", hba)
        atexit.register(self.destroy)

    def _run(self, cmd: list[str], check: bool = True) -> subprocess.CompletedProcess[str]:
        if self._as_root:
            cmd = ["runuser", "-u", "postgres", "--", *cmd]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
        if check and done.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed ({done.returncode}): {done.stderr.strip()[-2000:]}")
        return done

    def _write_as_server(self, path: Path, text: str) -> None:
        path.write_text(text)
        if self._as_root:
            shutil.chown(path, "postgres", "postgres")

    def start(self) -> None:
        for _attempt in range(3):
            self.port = self.port or _free_port()
            options = (f"-p {self.port} -k {self.sock} -h 127.0.0.1 -c fsync=off -c synchronous_commit=off "
                       "-c full_page_writes=off -c max_connections=40 -c shared_buffers=32MB")
            done = self._run([str(self.bin / "pg_ctl"), "-D", str(self.data), "-l", str(self.log), "-w", "-t", "60",
                              "-o", options, "start"], check=False)
            if done.returncode == 0:
                self.running = True
                return
            self.port = 0  # the port was taken meanwhile: another
        raise RuntimeError(f"PostgreSQL did not start: {self.log.read_text()[-2000:] if self.log.exists() else ''}")

    def stop(self, mode: str = "fast") -> None:
        if self.running:
            self._run([str(self.bin / "pg_ctl"), "-D", str(self.data), "-m", mode, "-w", "stop"], check=False)
            self.running = False

    def destroy(self) -> None:
        self.stop("immediate")
        shutil.rmtree(self.base, ignore_errors=True)
        shutil.rmtree(self.secrets, ignore_errors=True)

    # ------------------------------------------------------------------ SQL as the superuser
    def admin(self, sql: str, database: str = "postgres") -> None:
        import psycopg

        with psycopg.connect(host="127.0.0.1", port=self.port, user="postgres", dbname=database,
                             autocommit=True) as conn:
            conn.execute(sql)

    def setup_roles(self) -> None:
        for role in (OWNER, APP):
            secret = uuid.uuid4().hex
            self.admin(f"CREATE ROLE {role} LOGIN PASSWORD '{secret}'")
            path = self.secrets / role
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with open(fd, "w") as fh:
                fh.write(secret + "\n")

    def new_database(self) -> Database:
        """A fresh database owned by the owner role, migrated by it (``linarmpp archive upgrade``), with the
        application role's grants."""
        from app.archive.schema import grant_statements
        from app.archive.store import upgrade_archive

        name = f"archive_{uuid.uuid4().hex[:12]}"
        self.admin(f"CREATE DATABASE {name} OWNER {OWNER}")
        db = Database(name, self)
        upgrade_archive(url=db.url(OWNER), password_file=db.password_file(OWNER))
        import psycopg

        secret = (self.secrets / OWNER).read_text().strip()
        with psycopg.connect(host="127.0.0.1", port=self.port, user=OWNER, password=secret, dbname=name,
                             autocommit=True) as conn:
            for statement in grant_statements(APP):
                conn.execute(statement)
        return db


def start_server() -> PostgresServer:
    server = PostgresServer()
    try:
        server.start()
        server.setup_roles()
    except BaseException:
        server.destroy()
        raise
    return server


@contextlib.contextmanager
def server_or_skip() -> Iterator[PostgresServer]:
    """The session's server; skipped when none can start, a failure under CI=true."""
    try:
        server = start_server()
    except Exception as exc:
        message = f"a PostgreSQL server could not be started for the archive's tests: {exc}"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message)
        pytest.skip(message)
    try:
        yield server
    finally:
        server.destroy()
