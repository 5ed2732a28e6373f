"""The experiment harness's configuration: read from YAML, checked against ``config/schema.yaml`` (a mistake is one
line naming the key), and the render defaults filled in from :mod:`guiding.render.defaults`."""

from __future__ import annotations

import json
import os
from pathlib import Path

from guiding.errors import GuidingError
from guiding.render import defaults

PROJECT_ROOT = Path(__file__).resolve().parents[2]
SCHEMA = PROJECT_ROOT / "config" / "schema.yaml"
DEFAULT_CONFIG = PROJECT_ROOT / "config" / "config.yaml"
#: What a configuration's ``render`` leaves out: the renderer's own defaults.
RENDER_DEFAULTS = {"pass_spp": defaults.PASS_SPP, "max_depth": defaults.MAX_DEPTH}


class ConfigError(GuidingError):
    """The configuration is wrong; the message names the key and says what is expected."""


def load_config(path: str | os.PathLike) -> dict:
    import yaml

    try:
        with open(path) as file:
            data = yaml.safe_load(file)
    except OSError as error:
        raise ConfigError(f"cannot read config '{path}': {error.strerror}") from None
    except yaml.YAMLError as error:
        raise ConfigError(f"config '{path}' is not valid YAML: {str(error).splitlines()[0]}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"config '{path}' must be a mapping of keys to values")
    return data


def _key_path(parts) -> str:
    text = ""
    for part in parts:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else str(part))
    return text or "(top level)"


def _format_schema_error(error) -> str:
    """One line naming the offending key for a jsonschema ValidationError."""
    where = _key_path(error.absolute_path)
    if error.validator == "additionalProperties":
        allowed = sorted(error.schema.get("properties", {}))
        unknown = sorted(set(error.instance) - set(allowed)) if isinstance(error.instance, dict) else []
        if unknown and allowed:
            keys = ", ".join(f"'{k}'" for k in unknown)
            return f"{where}: unknown key {keys} (allowed: {', '.join(allowed)})"
        if unknown:  # a name → object mapping (scenes, methods, budgets): the value is what is wrong
            return f"{where}.{unknown[0]}: {error.message}"
    if error.validator == "required":
        return f"{where}: {error.message}"
    if error.validator == "enum":
        choices = ", ".join(json.dumps(c) for c in error.validator_value)
        return f"{where}: {json.dumps(error.instance)} is not one of {choices}"
    if error.validator == "oneOf" and isinstance(error.instance, dict) and {"spp", "seconds"} & set(error.schema.get(
            "properties", {})):
        given = sorted({"spp", "seconds"} & set(error.instance))
        return f"{where}: give exactly one of 'spp' and 'seconds' (got {' and '.join(given) or 'neither'})"
    if error.validator == "propertyNames":
        return f"{where}: bad name {json.dumps(error.instance)} (letters, digits and _ . + - only)"
    return f"{where}: {error.message}"


def validate_schema(config: dict, schema: str | os.PathLike = SCHEMA) -> dict:
    """Validate ``config`` against the JSON schema with ``snakemake.utils.validate`` (which fills in the schema's
    defaults, in place), then fill in the render defaults (:data:`RENDER_DEFAULTS`); a failure is one
    :class:`ConfigError` line naming the key."""
    from snakemake.exceptions import WorkflowError
    from snakemake.utils import validate

    try:
        validate(config, str(Path(schema).resolve()))
    except WorkflowError:
        import jsonschema
        from snakemake.common.configfile import _load_configfile

        schema_dict = _load_configfile(str(schema), filetype="Schema")
        best = jsonschema.exceptions.best_match(jsonschema.Draft202012Validator(schema_dict).iter_errors(config))
        raise ConfigError(_format_schema_error(best) if best is not None else "config does not match its schema") \
            from None
    for key, value in RENDER_DEFAULTS.items():
        config["render"].setdefault(key, value)
    return config
