"""``python -m m2s2hil.api > docs/openapi.json``: print the API's OpenAPI schema."""

import sys

from m2s2hil.api.app import openapi_json

sys.stdout.write(openapi_json())
