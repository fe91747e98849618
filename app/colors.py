"""Display colours of the part roles (swatches in the part tree and actor colours agree)."""

ROLE_COLOURS: dict[str | None, str] = {
    "femur": "#efe6cf",
    "tibia": "#e8dcbc",
    "fibula": "#dccfae",
    "patella": "#f4ecd8",
    "skin": "#e0ac8a",
    "flesh": "#c9605a",
    "ligament": "#4f8fe0",
    "meniscus": "#9b6fd0",
    "tendon": "#3fb7a8",
    "capsule": "#8fb050",
    "fixed": "#8a8f98",
}
UNASSIGNED_COLOUR = "#c8c8c8"
