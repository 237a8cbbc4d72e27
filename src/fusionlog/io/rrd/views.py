"""Blueprint pieces shared by the recordings' default layouts."""

from __future__ import annotations

from collections.abc import Sequence

import rerun.blueprint as rrb

from .stream import entity_path

__all__ = ["WHOLE_X", "query", "tabbed_blueprint", "time_series_view"]

_INF = rrb.TimeRangeBoundary.infinite()
#: The x axis a time-series view opens on: all its data. Without it the viewer opens a view of
#: more than a minute on the `time` timeline (heterogeneous.toml: 100 s; a long recorded log)
#: on -30 s .. +30 s about the cursor at 0: half the view empty, the rest of the data off it.
WHOLE_X = rrb.TimeAxis(view_range=rrb.TimeRange(start=_INF, end=_INF))


def query(*parts: str | int) -> str:
    """An entity-path query ("+ /a/b") from unescaped parts; append "/**" for a subtree."""
    return "+ /" + entity_path(*parts)


def time_series_view(
    name: str,
    contents: list[str],
    legend: bool = True,
    corner: str = "RightTop",
    y_range: tuple[float, float] | None = None,
) -> rrb.TimeSeriesView:
    """A time-series view of `contents` (queries), with its legend in `corner` or none;
    `y_range`: the y range it opens on (zooming out shows the rest), else the viewer's fit."""
    axis = {} if y_range is None else {"axis_y": rrb.ScalarAxis(range=y_range, zoom_lock=False)}
    return rrb.TimeSeriesView(
        origin="/",
        contents=contents,
        name=name,
        plot_legend=rrb.PlotLegend(corner=corner, visible=legend),
        axis_x=WHOLE_X,
        **axis,
    )


def tabbed_blueprint(
    tabs: Sequence[rrb.Container | rrb.View], timeline: str = "step"
) -> rrb.Blueprint:
    """The default blueprint: `tabs` with the first one open, side panels collapsed, the time
    panel on `timeline` (``step``, or ``time`` for instants at irregular times) and paused
    (the recordings are results, not a live feed)."""
    return rrb.Blueprint(
        rrb.Tabs(*tabs, active_tab=0),
        rrb.TimePanel(timeline=timeline, state="collapsed", play_state="paused"),
        collapse_panels=True,
    )
