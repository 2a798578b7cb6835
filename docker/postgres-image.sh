#!/usr/bin/env bash
# A stand-in for the PostgreSQL image docker/compose.scale.yaml names (postgres:15-bookworm)
# where no registry is reachable: Debian's postgresql-15 on the python:3.11-slim-bookworm
# base (docker/base-image.sh stands in for that one), with an entry point that does what
# the official image's does for this compose file: on an empty volume, initdb with
# POSTGRES_USER / POSTGRES_PASSWORD (scram-sha-256 over the network) and a database
# POSTGRES_DB; then the server, listening on every address.
#   DOCKER_HOST=unix:///tmp/docker.sock docker/postgres-image.sh
set -euo pipefail
name="${COVSLAM_POSTGRES_IMAGE:-postgres:15-bookworm}"
if docker image inspect "$name" >/dev/null 2>&1; then
    exit 0
fi
context="$(mktemp -d /tmp/covslam-pg-image.XXXXXX)"
trap 'rm -rf "$context"' EXIT
cat > "$context/entrypoint.sh" <<'SH'
#!/bin/sh
set -eu
bin=/usr/lib/postgresql/15/bin
export PGDATA="${PGDATA:-/var/lib/postgresql/data}"
mkdir -p "$PGDATA" /run/postgresql
chown postgres "$PGDATA" /run/postgresql
chmod 700 "$PGDATA"
if [ ! -s "$PGDATA/PG_VERSION" ]; then
    pw="$(mktemp)"
    printf '%s\n' "$POSTGRES_PASSWORD" > "$pw"
    chown postgres "$pw"
    runuser -u postgres -- "$bin/initdb" -D "$PGDATA" -U "$POSTGRES_USER" --pwfile="$pw" \
        --auth-local=trust --auth-host=scram-sha-256 -E UTF8 --locale=C.UTF-8 >/dev/null
    rm -f "$pw"
    echo "host all all all scram-sha-256" >> "$PGDATA/pg_hba.conf"
    runuser -u postgres -- "$bin/pg_ctl" -D "$PGDATA" -o "-c listen_addresses=''" -w start >/dev/null
    runuser -u postgres -- psql -q -U "$POSTGRES_USER" -d postgres \
        -c "CREATE DATABASE \"${POSTGRES_DB:-$POSTGRES_USER}\""
    runuser -u postgres -- "$bin/pg_ctl" -D "$PGDATA" -m fast -w stop >/dev/null
fi
exec setpriv --reuid=postgres --regid=postgres --init-groups \
    "$bin/postgres" -D "$PGDATA" -c listen_addresses='*'
SH
cat > "$context/Dockerfile" <<'DOCKERFILE'
FROM python:3.11-slim-bookworm
RUN apt-get update -q && apt-get install -y -q --no-install-recommends postgresql-15 \
    && rm -rf /var/lib/apt/lists/*
COPY entrypoint.sh /usr/local/bin/docker-entrypoint.sh
RUN chmod 755 /usr/local/bin/docker-entrypoint.sh
EXPOSE 5432
STOPSIGNAL SIGINT
ENTRYPOINT ["/usr/local/bin/docker-entrypoint.sh"]
DOCKERFILE
docker build --network host -q -t "$name" "$context" >/dev/null
