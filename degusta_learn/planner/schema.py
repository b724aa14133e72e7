"""JSON Schemas (draft 2020-12) of the plan request and the plan, for the server's OpenAPI description and for
clients that generate code from it. The checks that make a request valid are `PlanRequest.from_json` and the
planner's (tests/test_planner_server.py keeps these schemas in step with them); the schemas describe the form."""

from __future__ import annotations

from degusta_learn.planner.plan import PLAN_FORMAT, PLAN_VERSION
from degusta_learn.planner.request import (
    MAX_CONTEXT,
    MAX_METRES,
    MAX_OBJECTS,
    MAX_PLACEMENTS,
    MAX_POLYGON_POINTS,
    MAX_STEPS,
    MAX_TABLE_PIXELS,
    MAX_TABLES,
)
from degusta_learn.scene.validate import MAX_ID, MAX_TRIAL

_UNIT = {"type": "number", "minimum": 0, "maximum": 1}
_ID = {"type": "integer", "minimum": 0, "maximum": MAX_ID}
_POINT = {"type": "array", "items": _UNIT, "minItems": 2, "maxItems": 2}
_METRES = {"type": "array", "items": {"type": "number", "exclusiveMinimum": 0, "maximum": MAX_METRES},
           "minItems": 2, "maxItems": 2, "description": "width and height of the table image in metres"}
_PLACEMENT = {"type": "object", "additionalProperties": False, "required": ["object", "x", "y"],
              "properties": {"object": _ID, "x": _UNIT, "y": _UNIT, "rotation": {"type": "number"}}}
_ARRANGEMENT = {"type": "object", "additionalProperties": False, "required": ["table", "placements"],
                "properties": {"participant": {"type": ["string", "integer"]},
                               "trial": {"type": "integer", "minimum": 0, "maximum": MAX_TRIAL}, "table": _ID,
                               "placements": {"type": "array", "items": _PLACEMENT, "minItems": 1,
                                              "maxItems": MAX_PLACEMENTS}}}
_TABLE = {"type": "object", "additionalProperties": False, "required": ["width", "height", "surface"],
          "properties": {"id": _ID, "width": {"type": "integer", "minimum": 1, "maximum": MAX_TABLE_PIXELS},
                         "height": {"type": "integer", "minimum": 1, "maximum": MAX_TABLE_PIXELS},
                         "surface": {"type": "array", "items": _POINT, "minItems": 3, "maxItems": MAX_POLYGON_POINTS},
                         "name": {"type": "string", "maxLength": 100}, "image": {"type": "string"}, "metres": _METRES}}
_KNOWN_TABLE = {"type": "object", "additionalProperties": False, "required": ["id"],
                "properties": {"id": _ID, "metres": _METRES}}

REQUEST_SCHEMA = {
    "title": "PlanRequest", "type": "object", "additionalProperties": False, "required": ["table"],
    "description": "A plan request (docs/planner.md): whose table (arrangements inline, or a participant of the "
                   "planner's dataset), which table, the objects on hand.",
    "properties": {
        "table": {"oneOf": [_ID, _KNOWN_TABLE, _TABLE]},
        "arrangements": {"type": "array", "items": _ARRANGEMENT, "maxItems": MAX_CONTEXT},
        "participant": {"type": ["string", "integer"]},
        "trials": {"type": "array", "items": {"type": "integer", "minimum": 0, "maximum": MAX_TRIAL},
                   "maxItems": MAX_CONTEXT, "uniqueItems": True},
        "dataset": {"type": "string", "description": "a dataset folder (refused by `degusta serve`)"},
        "catalog": {"type": "array", "items": {"type": "object"}, "maxItems": MAX_OBJECTS},
        "tables": {"type": "array", "items": {**_TABLE, "required": ["id", "width", "height", "surface"]},
                   "maxItems": MAX_TABLES},
        "objects": {"type": "array", "items": _ID, "minItems": 1, "maxItems": MAX_OBJECTS, "uniqueItems": True},
        "n_objects": {"type": "integer", "minimum": 1, "maximum": MAX_STEPS},
    },
}

_NUMBER_OR_NULL = {"type": ["number", "null"]}
PLAN_SCHEMA = {
    "title": "Plan", "type": "object", "required": ["format", "version", "method", "config_sha256", "table", "steps",
                                                    "failed", "diagnostics"],
    "properties": {
        "format": {"const": PLAN_FORMAT}, "version": {"const": PLAN_VERSION},
        "method": {"type": "string"}, "config_sha256": {"type": "string"},
        "table": {"type": "object", "required": ["id", "width", "height", "surface", "metres"],
                  "properties": {"id": _ID, "name": {"type": "string"}, "width": {"type": "integer"},
                                 "height": {"type": "integer"}, "surface": {"type": "array", "items": _POINT},
                                 "metres": {"oneOf": [{"type": "null"}, _METRES]}}},
        "steps": {"type": "array", "items": {
            "type": "object", "required": ["step", "object", "type", "x", "y", "rotation", "x_m", "y_m"],
            "properties": {"step": {"type": "integer", "minimum": 1}, "object": _ID, "type": {"type": "string"},
                           "x": _UNIT, "y": _UNIT, "rotation": {"type": "number", "minimum": 0, "exclusiveMaximum": 360},
                           "x_m": _NUMBER_OR_NULL, "y_m": _NUMBER_OR_NULL}}},
        "failed": {"type": "boolean"},
        "diagnostics": {"type": "object", "required": ["context", "failures", "cost_usd", "replaced", "dropped",
                                                       "clamped", "cut", "method"],
                        "properties": {"context": {"type": "integer"}, "failures": {"type": "array"},
                                       "cost_usd": _NUMBER_OR_NULL, "replaced": {"type": "array"},
                                       "dropped": {"type": "array"}, "clamped": {"type": "array"},
                                       "cut": {"type": "integer"}, "method": {"type": "object"}}},
    },
}

ERROR_SCHEMA = {"title": "Error", "type": "object", "required": ["detail"],
                "properties": {"detail": {"type": "string", "description": "one line, as `degusta plan` prints it"}}}

__all__ = ["ERROR_SCHEMA", "PLAN_SCHEMA", "REQUEST_SCHEMA"]
