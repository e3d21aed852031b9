# m2s2hil capture daemon.
#
# Build:  docker build -t m2s2hil .
# Run on the simulated rig (loopback only inside the container, so publish with a token):
#   docker run --rm -p 8750:8750 -e M2S2HIL_TOKEN=change-me -v m2s2-data:/data m2s2hil
# Run on a real rig: pass the devices through and mount a rig file, e.g.
#   docker run --rm -p 8750:8750 -e M2S2HIL_TOKEN=change-me \
#     --device /dev/ttyUSB0 --device /dev/ttyUSB1 \
#     --device /dev/bus/usb \            # the U3V camera (or one /dev/bus/usb/BBB/DDD node)
#     -v /etc/m2s2hil/rig.toml:/config/rig.toml:ro -v /srv/m2s2:/data \
#     m2s2hil m2s2hil serve --host 0.0.0.0 --port 8750 --rig /config/rig.toml --resume
# The user in the image is in the dialout group (serial ports); USB nodes passed with
# --device need to be readable by it (a udev rule on the host, or --group-add).
FROM python:3.11-slim-bookworm

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    M2S2HIL_DATA=/data

# libusb is what pyusb's real backend loads to reach the camera.
# hadolint ignore=DL3008
RUN apt-get update \
    && apt-get install -y --no-install-recommends libusb-1.0-0 \
    && rm -rf /var/lib/apt/lists/*

WORKDIR /app
COPY pyproject.toml README.md ./
COPY m2s2hil ./m2s2hil
COPY drivers ./drivers
COPY protocols ./protocols
COPY simulators ./simulators
# The runtime dependencies only: what capture and the daemon need. The `analysis` extra
# (Dask for `evaluate`, the ground truth of `bench demosaic`) stays out of the daemon's image.
RUN pip install --no-cache-dir .

RUN useradd --create-home --uid 10001 --groups dialout m2s2 \
    && mkdir -p /data \
    && chown m2s2:m2s2 /data
USER 10001
VOLUME ["/data"]
EXPOSE 8750

HEALTHCHECK --interval=30s --timeout=5s --start-period=20s --retries=3 \
    CMD ["python", "-c", "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8750/healthz', timeout=4)"]

CMD ["m2s2hil", "serve", "--host", "0.0.0.0", "--port", "8750"]
