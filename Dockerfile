# elastreg: the registration API (`elastreg serve`) on port 8000, with the shipped models.
#
#   docker build -t elastreg .
#   docker run --rm -p 127.0.0.1:8000:8000 -e ELASTREG_API_TOKENS="$(cat tokens.csv)" elastreg
#   docker run --rm -p 8000:8000 -v $PWD/tokens.txt:/run/tokens.txt:ro -e ELASTREG_SOLVER_THREADS=4 \
#       elastreg elastreg serve --host 0.0.0.0 --token-file /run/tokens.txt
#
# The container listens on 0.0.0.0, so it needs tokens (it refuses to start without them; see
# docs/deployment.md). More cores: one process with ELASTREG_SOLVER_THREADS, not --workers (an
# HTTP session lives in the process that opened it, and a second worker answers its frames
# 404); more machines: one container each behind a proxy with session affinity. TLS: a TLS
# proxy in front, or --ssl-certfile/--ssl-keyfile. The same install as the README (CPU torch
# first, then the package); nothing is fetched at run time. Settings come from ELASTREG_*
# variables (service/config.py).
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

WORKDIR /app

RUN pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu

# the server's dependencies in their own layer (the base install: no trainer, benchmark or
# client extras), rebuilt only when pyproject.toml changes, not at every source edit
COPY pyproject.toml ./
RUN python -c "import tomllib; print('\n'.join(tomllib.load(open('pyproject.toml', 'rb'))['project']['dependencies']))" \
        > /tmp/requirements.txt \
    && pip install -r /tmp/requirements.txt && rm /tmp/requirements.txt

COPY README.md ./
COPY service ./service
COPY clients ./clients
RUN pip install --no-deps .

COPY model_store ./model_store

RUN useradd --create-home --uid 10001 elastreg
USER elastreg

# the installed package does not sit beside model_store/: name the store; numba caches its
# compiled distance kernel somewhere writable
ENV ELASTREG_STORE=/app/model_store \
    NUMBA_CACHE_DIR=/tmp/numba-cache

EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s \
    CMD python -c "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/health', timeout=4)"

CMD ["elastreg", "serve", "--host", "0.0.0.0", "--port", "8000"]
