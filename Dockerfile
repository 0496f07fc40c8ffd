# gradsep reconstruction service: serving dependencies only (no torch, no mitsuba), exported models baked in.
#
#   docker build -t gradsep . && docker run -p 8000:8000 gradsep
#
# Settings come from GRADSEP_* environment variables (docs/service.md), e.g.
#   docker run -p 8000:8000 -e GRADSEP_TOKEN=... -e GRADSEP_CONCURRENCY=2 gradsep
# The build context must contain models/ (the exported *.onnx; an empty folder serves the Poisson methods only).

FROM python:3.11-slim AS build
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /src
# Only what the serving install needs; renderer/ and training/ stay out (gradsep skips absent command groups).
COPY pyproject.toml setup.py README.md ./
COPY gradsep/ gradsep/
COPY model/ model/
COPY service/ service/
RUN python -m venv /opt/venv && /opt/venv/bin/pip install ".[serve]"

FROM python:3.11-slim
ENV PATH=/opt/venv/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    GRADSEP_MODELS=/app/models \
    NUMBA_CACHE_DIR=/tmp/gradsep-numba
RUN useradd --system --uid 10001 --user-group --home-dir /app --shell /usr/sbin/nologin gradsep
COPY --from=build /opt/venv /opt/venv
WORKDIR /app
# Owned by root, read-only to the service user: a compromised process cannot swap the models.
COPY models/ /app/models/
USER gradsep
EXPOSE 8000
# Liveness only (cheap, no auth); orchestrators should route traffic on GET /readyz.
HEALTHCHECK --interval=30s --timeout=5s --start-period=30s --retries=3 \
    CMD ["python", "-c", "import sys, urllib.request; sys.exit(0 if urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=4).status == 200 else 1)"]
CMD ["gradsep", "serve", "--host", "0.0.0.0", "--port", "8000"]
