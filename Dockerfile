# The nlpsf service: REST API under /api/v1, docs at /docs, the page at /.
# Serves the shipped precomputed slope tables; no simulation is needed at start.
#
#   ../shared/tools/container build localhost/nlpsf:dev
#   ../shared/tools/container run localhost/nlpsf:dev            # listens on 0.0.0.0:8000
#
# Configuration by environment (see README): NLPSF_WORKERS (HTTP worker processes), NLPSF_JOB_WORKERS
# (simulation processes), NLPSF_MAX_QUEUE, NLPSF_MAX_* limits, NLPSF_DB_PATH (default /data, a volume).
# The container listens on all its interfaces (a published port needs it): on a shared network set
# NLPSF_API_KEYS (comma-separated keys required on /api/v1) and NLPSF_ALLOWED_HOSTS (Host header check).
ARG BASE_IMAGE=python:3.11-slim
FROM ${BASE_IMAGE}

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    VIRTUAL_ENV=/opt/venv \
    PATH=/opt/venv/bin:$PATH

# Debian's system Python refuses pip installs: everything goes into a venv.
RUN python -m venv /opt/venv

WORKDIR /srv/nlpsf
# The package as users install it: the library, the web layer (app/ -> nlpsf.web) and the page
# (static/ -> nlpsf.web.static) in one installed distribution; the source tree is not kept.
COPY pyproject.toml README.md LICENSE ./
COPY nlpsf ./nlpsf
COPY app ./app
COPY static ./static
COPY docs ./docs
RUN pip install --no-cache-dir . && rm -rf /srv/nlpsf/* && python -c "from nlpsf.slopes import tables as t; t.load_tables().load_all()"

# A system user without a login; written directly because minimal Debian bases lack useradd.
RUN echo "nlpsf:x:10001:10001:nlpsf service:/srv/nlpsf:/usr/sbin/nologin" >> /etc/passwd \
    && echo "nlpsf:x:10001:" >> /etc/group \
    && mkdir -p /data && chown 10001:10001 /data
USER 10001:10001

ENV NLPSF_DB_PATH=/data/jobs.sqlite3 \
    NLPSF_WORKERS=2 \
    NLPSF_JOB_WORKERS=1 \
    PORT=8000
VOLUME ["/data"]
EXPOSE 8000

HEALTHCHECK --interval=30s --timeout=5s --start-period=20s --retries=3 \
    CMD python -c "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:%s/api/v1/health' % os.environ.get('PORT', '8000'), timeout=4)"

CMD ["sh", "-c", "exec nlpsf serve --host 0.0.0.0 --port \"$PORT\""]
