#!/usr/bin/env bash
# Start Debian's PostgreSQL cluster if it is not answering, give 127.0.0.1 trust auth if the
# tests' user cannot log in, and create the `test` database the tests connect to. Idempotent:
# on a machine where all of that holds it changes nothing.
set -euo pipefail
ver="$(ls /etc/postgresql 2>/dev/null | sort -V | tail -1 || true)"
if [ -z "$ver" ]; then
  echo "ci-postgres: no PostgreSQL cluster under /etc/postgresql (is the postgresql package installed?)" >&2
  exit 1
fi
if ! pg_isready -h 127.0.0.1 -q; then
  pg_ctlcluster --skip-systemctl-redirect "$ver" main start
  for _ in $(seq 30); do pg_isready -h 127.0.0.1 -q && break; sleep 1; done
fi
q() { psql -w -h 127.0.0.1 -U postgres -d postgres -v ON_ERROR_STOP=1 -qtAc "$1"; }
if ! q "SELECT 1" >/dev/null 2>&1; then
  hba="/etc/postgresql/$ver/main/pg_hba.conf"
  echo "ci-postgres: trust auth for 127.0.0.1 and ::1 in $hba (a CI machine's own cluster)"
  sed -i '1i host all all 127.0.0.1/32 trust\nhost all all ::1/128 trust' "$hba"
  pg_ctlcluster --skip-systemctl-redirect "$ver" main reload
  sleep 1
fi
[ "$(q "SELECT 1 FROM pg_database WHERE datname = 'test'")" = "1" ] || q "CREATE DATABASE test"
pg_isready -h 127.0.0.1
