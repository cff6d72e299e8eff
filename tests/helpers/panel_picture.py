"""A picture of the Blender add-on's panel, drawn from what its `draw()` laid out.

Headless Blender (the `bpy` module) has no window manager: no region is drawn, so no real
screenshot of a sidebar panel can be taken. `tests/blender/addon_in_blender.py` hands the panel's
`draw()` a stand-in layout that records every label, property and operator as one text line
(failing like Blender on a missing property or an unregistered operator); this module draws
those lines the way Blender's dark theme lays them out (rows, value fields, check boxes,
buttons, icons as glyphs), so a person can look at what an artist would see. The caption of
every picture says it was drawn from the layout, not captured from Blender.

Line grammar (`addon_in_blender.PanelText`): two spaces per nesting level, then
`<[ICON] text>` an operator button, `[ICON] text` a label with an icon, `name: value` a
property (`value%` a slider), anything else a label.
"""

from __future__ import annotations

from pathlib import Path

#: Blender's default dark theme (Preferences > Themes > User Interface), RGB 0..1
_BG, _HEADER, _FIELD, _BUTTON, _TEXT = "#303030", "#1d1d1d", "#1d1d1d", "#545454", "#e6e6e6"
_ICON = {"ERROR": ("!", "#d64545"), "INFO": ("i", "#4d88d6"), "CANCEL": ("x", "#9a9a9a"),
         "EXPORT": ("^", "#9a9a9a"), "IMPORT": ("v", "#9a9a9a"), "URL": ("@", "#9a9a9a")}
_ROW = 0.3  # inches per row


def parse_line(line: str) -> dict:
    """One recorded line -> {kind: 'button'|'label'|'prop', depth, icon, text, value}."""
    depth = (len(line) - len(line.lstrip(" "))) // 2
    s = line.strip()
    item = {"depth": depth, "icon": None, "text": s, "value": None, "kind": "label"}
    if s.startswith("<") and s.endswith(">"):
        item["kind"], s = "button", s[1:-1]
    if s.startswith("[") and "]" in s:
        item["icon"], s = s[1:s.index("]")], s[s.index("]") + 1:].lstrip()
    item["text"] = s
    if item["kind"] == "label" and item["icon"] is None and ": " in s:
        item["kind"] = "prop"
        item["text"], item["value"] = s.split(": ", 1)
    return item


def _icon(ax, icon: str | None, x: float, y: float) -> None:  # noqa: ANN001
    """An icon as a glyph in a coloured disc (Blender's icon sheet is not in the bpy wheel)."""
    if not icon or icon in ("NONE", "BLANK1"):
        return
    glyph, colour = _ICON.get(icon, (icon[:1].lower(), "#9a9a9a"))
    ax.text(x, y, glyph, color="white", ha="center", va="center", fontsize=6,
            fontweight="bold", bbox={"boxstyle": "circle,pad=0.25", "fc": colour, "ec": "none"})


def draw_panel(lines: list[str], path: Path | str, *, caption: str,
               title: str = "texelbake") -> Path:
    """Draw the recorded panel `lines` to a PNG at `path` (260 px wide per 2.6 in at 100 dpi)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import FancyBboxPatch, Rectangle

    items = [parse_line(ln) for ln in lines if ln.strip()]
    n = len(items) + 2  # header and caption
    fig = plt.figure(figsize=(3.4, _ROW * n), dpi=110)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_xlim(0, 1)
    ax.set_ylim(n, 0)
    ax.axis("off")
    fig.patch.set_facecolor(_BG)
    ax.add_patch(Rectangle((0, 0), 1, 1, color=_HEADER))
    ax.text(0.04, 0.55, "\u25be  " + title, color=_TEXT, va="center", fontsize=9,
            fontweight="bold")
    for row, it in enumerate(items, start=1):
        y, x = row + 0.5, 0.04 + 0.04 * it["depth"]
        has_icon = bool(it["icon"]) and it["icon"] != "NONE"
        tx = x + (0.07 if has_icon else 0.0)
        if it["kind"] == "button":
            ax.add_patch(FancyBboxPatch((x, row + 0.12), 0.96 - x, 0.76,
                                        boxstyle="round,pad=0,rounding_size=0.02",
                                        color=_BUTTON))
            ax.text((x + 0.96) / 2, y, it["text"], color=_TEXT, ha="center", va="center",
                    fontsize=8)
            _icon(ax, it["icon"], x + 0.035, y)
        elif it["kind"] == "prop":
            value = str(it["value"])
            ax.text(tx, y, it["text"], color=_TEXT, va="center", fontsize=8)
            if value in ("True", "False"):
                ax.add_patch(Rectangle((0.5, row + 0.25), 0.05, 0.5, color=_FIELD))
                if value == "True":
                    ax.text(0.525, y, "\u2713", color=_TEXT, ha="center", va="center",
                            fontsize=8)
                continue
            ax.add_patch(FancyBboxPatch((0.5, row + 0.12), 0.46, 0.76,
                                        boxstyle="round,pad=0,rounding_size=0.02",
                                        color=_FIELD))
            if value.endswith("%"):  # a slider: the filled part is the fraction
                frac = min(max(float(value[:-1]) / 100.0, 0.0), 1.0)
                ax.add_patch(Rectangle((0.5, row + 0.12), 0.46 * frac, 0.76, color="#4772b3"))
            ax.text(0.73, y, value if len(value) <= 30 else value[:29] + "\u2026",
                    color=_TEXT, ha="center", va="center", fontsize=7)
        else:  # Blender clips a label at the sidebar's edge: so does the picture
            text = it["text"] if len(it["text"]) <= 46 else it["text"][:45] + "\u2026"
            ax.text(tx, y, text, color=_TEXT, va="center", fontsize=8)
        if it["kind"] != "button":
            _icon(ax, it["icon"], x + 0.03, y)
    ax.text(0.5, n - 0.5, caption, color="#9a9a9a", ha="center", va="center", fontsize=5.5,
            style="italic", wrap=True)
    path = Path(path)
    fig.savefig(path, facecolor=_BG)
    plt.close(fig)
    return path
