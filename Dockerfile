# motcomp: the compensator service in a container.
#
#   docker build -t motcomp .
#   docker run --rm --network host --stop-timeout 30 \
#       -v /etc/motcomp:/config:ro motcomp            # runs `motcomp run --config /config/motcomp.toml`
#
# SIGTERM (docker stop) parks the platform at neutral before exiting: give it the time
# (--stop-timeout longer than loop.park_timeout_s).  See docs/DEPLOYMENT.md.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

WORKDIR /opt/motcomp
COPY pyproject.toml README.md ./
COPY motcomp ./motcomp
COPY config ./config
RUN pip install --no-cache-dir . \
    && groupadd --system --gid 10001 motcomp \
    && useradd --system --no-create-home --uid 10001 --gid 10001 --shell /usr/sbin/nologin motcomp \
    && mkdir -p /config \
    && cp config/motcomp.toml config/motcomp.dbc /config/

USER 10001:10001
VOLUME ["/config"]
EXPOSE 7447
STOPSIGNAL SIGTERM
ENTRYPOINT ["motcomp"]
CMD ["run", "--config", "/config/motcomp.toml"]
