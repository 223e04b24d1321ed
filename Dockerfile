# motcomp: the compensator service in a container.
#
#   docker build -t motcomp .
#   docker run --rm --network host --stop-timeout 30 \
#       -v /etc/motcomp:/config:ro motcomp            # runs `motcomp run --config /config/motcomp.toml`
#
# SIGTERM (docker stop) parks the platform at neutral before exiting: give it the time
# (--stop-timeout longer than loop.park_timeout_s).  See docs/DEPLOYMENT.md.
# Build stage: the wheel (it carries config/ as motcomp/_config, and the tick compiled by mypyc:
# hence a C compiler here; see motcomp/core/native.py).
FROM python:3.11-slim AS build
# hadolint ignore=DL3008
RUN apt-get update \
    && apt-get install -y --no-install-recommends gcc libc6-dev \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /src
COPY pyproject.toml setup.py MANIFEST.in README.md ./
COPY motcomp ./motcomp
COPY config ./config
RUN pip wheel --no-cache-dir --no-deps -w /wheels .

# Run stage.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

WORKDIR /opt/motcomp
COPY --from=build /wheels /wheels
COPY config/motcomp.toml config/motcomp.dbc /config/
RUN pip install --no-cache-dir /wheels/*.whl \
    && rm -rf /wheels \
    && groupadd --system --gid 10001 motcomp \
    && useradd --system --no-create-home --uid 10001 --gid 10001 --shell /usr/sbin/nologin motcomp

USER 10001:10001
VOLUME ["/config"]
EXPOSE 7447
STOPSIGNAL SIGTERM
ENTRYPOINT ["motcomp"]
CMD ["run", "--config", "/config/motcomp.toml"]
