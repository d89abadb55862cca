"""Land-cover classes of the demo scene (codes 1..N in every label raster; 0 = no data)."""

from __future__ import annotations

ROAD, PARKING, CONCRETE, BARE_SOIL, GRASS, TREE, HOUSE, TALL_BUILDING, WATER, VEHICLE = range(1, 11)

CLASSES: dict[int, dict[str, object]] = {
    ROAD: {"name": "road", "color": [60, 60, 64], "description": "asphalt streets and avenues"},
    PARKING: {"name": "parking", "color": [120, 120, 128], "description": "asphalt lots and yards"},
    CONCRETE: {
        "name": "concrete",
        "color": [200, 200, 190],
        "description": "sidewalks, plazas, driveways, paths",
    },
    BARE_SOIL: {"name": "bare_soil", "color": [170, 130, 90], "description": "vacant lots, dirt"},
    GRASS: {
        "name": "grass",
        "color": [120, 200, 80],
        "description": "lawns and parks (green to dry)",
    },
    TREE: {"name": "tree", "color": [20, 110, 30], "description": "tree crowns 5-20 m"},
    HOUSE: {
        "name": "house",
        "color": [220, 120, 60],
        "description": "low buildings: houses 4-9 m, low-rise commercial/industrial < 13 m",
    },
    TALL_BUILDING: {
        "name": "tall_building",
        "color": [200, 40, 40],
        "description": "mid- and high-rise buildings 15-120 m",
    },
    WATER: {"name": "water", "color": [30, 80, 200], "description": "ponds and swimming pools"},
    VEHICLE: {"name": "vehicle", "color": [250, 230, 0], "description": "cars and trucks"},
}

# ASPRS LAS classification written for the points of each class
LAS_CLASS = {
    ROAD: 2,
    PARKING: 2,
    CONCRETE: 2,
    BARE_SOIL: 2,
    GRASS: 2,
    TREE: 5,
    HOUSE: 6,
    TALL_BUILDING: 6,
    WATER: 9,
    VEHICLE: 1,
}


def classes_json() -> dict[str, dict[str, object]]:
    """The content of truth/classes.json: code (as string) -> name, colour, description."""
    return {str(k): dict(v) for k, v in CLASSES.items()}
