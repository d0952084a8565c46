"""Offline JSON-schema validation of STAC items against the extension schemas they declare.

The extension schemas are files under ``tests/data/stac-schemas/<host>/<path>`` (their
canonical URL without ``https://``; provenance and licences in its README.md), the GeoJSON
schemas are the ones pystac ships. A ``$ref`` to anything else is unresolvable and fails:
nothing is fetched."""
import json
from pathlib import Path

SCHEMAS = Path(__file__).parent / "data" / "stac-schemas"


def registry():
    """A ``referencing`` registry of every local schema under its canonical URL."""
    import pystac
    from referencing import Registry, Resource
    res = []
    for p in SCHEMAS.rglob("*.json"):
        res.append(("https://" + p.relative_to(SCHEMAS).as_posix(),
                    Resource.from_contents(json.loads(p.read_text(encoding="utf-8")))))
    geojson = Path(pystac.__file__).parent / "validation" / "jsonschemas" / "geojson"
    for p in geojson.glob("*.json"):
        res.append((f"https://geojson.org/schema/{p.name}",
                    Resource.from_contents(json.loads(p.read_text(encoding="utf-8")))))
    return Registry().with_resources(res)


def validate_extensions(doc: dict, reg=None) -> list[str]:
    """Validate ``doc`` (a STAC item as JSON) against the schema of every extension it
    declares (jsonschema, draft 7, local registry); raise on the first error. Returns the
    schema URLs used. A declared extension without a local schema fails."""
    from jsonschema import Draft7Validator
    reg = reg or registry()
    used = []
    for url in doc.get("stac_extensions", []):
        path = SCHEMAS / url.removeprefix("https://")
        assert path.exists(), f"no local schema for {url}"
        schema = json.loads(path.read_text(encoding="utf-8"))
        Draft7Validator(schema, registry=reg).validate(doc)
        used.append(url)
    return used


def validator_schema_map() -> dict[str, str]:
    """stac-validator's ``schema_map``: every schema a catalogue of ours refers to, by its
    URL, mapped to a local file (the STAC core and GeoJSON schemas from pystac's wheel, the
    extensions from SCHEMAS). stac-validator looks the core schemas' relative ``$ref``s up
    in the map as written ("common.json", "../../item-spec/json-schema/common.json"), so
    those are mapped too."""
    import pystac
    shipped = Path(pystac.__file__).parent / "validation" / "jsonschemas"
    core = sorted((shipped / "stac-spec" / "v1.1.0").glob("*.json"))
    out = {f"https://schemas.stacspec.org/v1.1.0/{kind}-spec/json-schema/{p.name}": str(p)
           for kind in ("item", "catalog", "collection") for p in core}
    out.update({p.name: str(p) for p in core})
    out.update({f"../../item-spec/json-schema/{p.name}": str(p) for p in core})
    out.update({f"https://geojson.org/schema/{p.name}": str(p)
                for p in (shipped / "geojson").glob("*.json")})
    out.update({"https://" + p.relative_to(SCHEMAS).as_posix(): str(p)
                for p in SCHEMAS.rglob("*.json")})
    return out
