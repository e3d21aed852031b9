FROM python:3.11-slim-bookworm
WORKDIR /app
COPY . /app
RUN pip install --no-cache-dir .
CMD ["m2s2hil", "--help"]
