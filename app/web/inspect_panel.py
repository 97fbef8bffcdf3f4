"""The Inspect tab: pick a state, see NN / greedy / lookahead side by side, the Q of every
candidate split into feature contributions (table and bar plot), a lookahead search running in
the background with its tree, and one candidate's registration drawn in 3D (/inspect/...).
"""

from __future__ import annotations

import io
import logging
import threading
from collections.abc import Callable
from contextlib import AbstractContextManager

import numpy as np
import viser

from knotlab.app.web.geometry import tube_faces, tube_vertices
from knotlab.app.web.inspect import Inspector, InspectView, RegistrationView
from knotlab.app.web.scene import CLOUD_COLOUR, ROPE_COLOUR, ROPE_RADIUS
from knotlab.core.execution.apply import ActionOutcome
from knotlab.core.selection.explain import lookahead_tree, search_tree_lines
from knotlab.core.textinput import whole_number

log = logging.getLogger(__name__)
SOURCES = ("current labelling state", "training start", "test task")
N_BARS = 8  # feature contributions plotted per candidate
SCENE_CLOUD = CLOUD_COLOUR
DEMO_CLOUD = (150, 150, 150)
WARPED_CLOUD = (0, 158, 115)
PAIR_COLOUR = (230, 159, 0)
MODEL_AFTER = (120, 120, 120)  # the rope after candidate A in the agent's model
WORLD_AFTER = (204, 121, 167)  # ... and in the world unlike the model
# Worlds a researcher can compare the agent's model with (physics setting names).
COMPARE_WORLDS = (
    "mass+50",
    "table_friction-50",
    "rope_friction-50",
    "damping+50",
    "grip_force-50",
    "grasp_reach-50",
    "gripper_speed+50",
    "settle_time-50",
    "length+25",
    "combined25",
    "combined50",
)


# The bar plot is drawn at the panel's width (about 350 px on screen) at twice its pixels, one
# candidate under the other, so that its text reads at about 12 px in the browser.
PLOT_WIDTH_IN = 4.4
PLOT_DPI = 160
PLOT_FONT_PT = 11
PLOT_ROW_IN = 2.9  # height per candidate


def contribution_plot(view: InspectView, demos: list[int], keys: tuple[str, ...]) -> np.ndarray:
    """A bar plot (RGB image) of the largest feature contributions of one or two candidates,
    one under the other, sized for the side panel."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from PIL import Image

    fig, axes = plt.subplots(
        len(demos), 1, figsize=(PLOT_WIDTH_IN, PLOT_ROW_IN * len(demos)), squeeze=False
    )
    for ax, a in zip(axes[:, 0], demos, strict=True):
        parts = view.contributions.get(a, [])[:N_BARS][::-1]
        names = [p.name for p in parts]
        values = [p.contribution for p in parts]
        ax.barh(names, values, color=["#009e73" if v >= 0 else "#d55e00" for v in values])
        ax.axvline(0, color="k", lw=0.6)
        q = next((r.q for r in view.ranking if r.demo_index == a), None)
        title = f"{keys[a]}  Q = {q:.2f}" if q is not None else keys[a]
        ax.set_title(title, fontsize=PLOT_FONT_PT + 1)
        ax.tick_params(labelsize=PLOT_FONT_PT)
        ax.set_xlabel("weight x standardised feature", fontsize=PLOT_FONT_PT)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=PLOT_DPI)
    plt.close(fig)
    buf.seek(0)
    return np.asarray(Image.open(buf).convert("RGB"))


def registration_legend() -> str:
    """What each colour of the registration view is (HTML swatches in markdown)."""

    def swatch(rgb: tuple[int, int, int], mark: str) -> str:
        r, g, b = rgb
        return f'<span style="color: rgb({r},{g},{b}); font-size: 1.2em">{mark}</span>'

    return "  \n".join(
        [
            "**Registration view**",
            f"{swatch(ROPE_COLOUR, '━')} the inspected rope",
            f"{swatch(SCENE_CLOUD, '●')} its observed cloud",
            f"{swatch(DEMO_CLOUD, '●')} A's demo cloud where it was recorded",
            f"{swatch(WARPED_CLOUD, '◆')} A's demo cloud warped onto this rope",
            f"{swatch(PAIR_COLOUR, '─')} each warped point to its nearest observed point",
        ]
    )


def _swatch(rgb: tuple[int, int, int]) -> str:
    """A coloured block for a markdown legend."""
    return f'<span style="color: rgb{rgb}">━━</span>'


class InspectPanel:
    """The Inspect tab of one browser tab (its own Inspector and simulator)."""

    def __init__(
        self,
        client: viser.ClientHandle,
        inspector: Inspector,
        current_nodes: Callable[[], np.ndarray | None],
        start_nodes: Callable[[str, int], np.ndarray],
        drawing: Callable[..., AbstractContextManager[bool]],
        frame: Callable[[np.ndarray], None],
        back: Callable[[], None],
    ) -> None:
        self.client = client
        self.inspector = inspector
        self._current_nodes = current_nodes
        self._start_nodes = start_nodes
        # drawing(enter=...) holds the 3D view for Inspect (showing it first if ``enter``) and
        # says whether Inspect's state is still the one on screen.
        self._drawing = drawing
        self._frame = frame  # point the camera at these points
        self._lock = threading.Lock()
        gui = client.gui
        self.source = gui.add_dropdown("State", SOURCES)
        # No min: a number out of range reaches the server, which says what the range is.
        self.index = gui.add_number("Number", 0, step=1)
        self.inspect_button = gui.add_button("Inspect", icon=viser.Icon.SEARCH)
        # Why the last Inspect did not load (the state inspected before stays as it was).
        self.error = gui.add_markdown("")
        self.back_button = gui.add_button(
            "Back to the labelling view", hint="the 3D view shows the inspected state until then"
        )
        self.choices = gui.add_markdown("Pick a state and press Inspect.")
        self.search_button = gui.add_button("Run lookahead(2, 5)", disabled=True)
        self.search_bar = gui.add_progress_bar(0.0, visible=False, animated=True)
        self.search_status = gui.add_markdown("")
        self.keep_search_button = gui.add_button(
            "Keep the choice so far",
            color="green",
            icon=viser.Icon.CHECK,
            visible=False,
            hint="stop the search: the choice of the levels it finished stands",
        )
        self.cancel_search_button = gui.add_button(
            "Cancel the search", color="red", icon=viser.Icon.X, visible=False
        )
        self.tree = gui.add_markdown("")
        self.table = gui.add_markdown("")
        self.cand_a = gui.add_dropdown("Candidate A", ("-",))
        self.cand_b = gui.add_dropdown("Candidate B", ("-",))
        self.plot = gui.add_image(np.full((10, 10, 3), 255, np.uint8), label="Q contributions")
        self.compare = gui.add_markdown("")
        self.show_3d = gui.add_checkbox("Show A's registration in 3D", False)
        self.legend = gui.add_markdown(registration_legend(), visible=False)
        self.compare_world = gui.add_dropdown(
            "World unlike the model", COMPARE_WORLDS, hint="a physics setting (docs/robustness.md)"
        )
        self.compare_button = gui.add_button(
            "Simulate A in the model and in that world", icon=viser.Icon.PLAYER_PLAY
        )
        self.compare_result = gui.add_markdown("")
        self._keys_to_index: dict[str, int] = {}
        self._shown_level = 0  # the search level whose choice the panel shows
        self.inspect_button.on_click(lambda _e: self.run_inspect())
        self.back_button.on_click(lambda _e: back())
        self.search_button.on_click(lambda _e: self.run_search())
        self.cancel_search_button.on_click(lambda _e: self.cancel_search())
        self.keep_search_button.on_click(lambda _e: self.keep_search())
        self.cand_a.on_update(lambda _e: self.show_candidates())
        self.cand_b.on_update(lambda _e: self.show_candidates())
        self.show_3d.on_update(lambda _e: self.draw_3d(reframe=True))
        self.compare_button.on_click(lambda _e: self.run_compare())

    # ------------------------------------------------------------------ actions
    def run_inspect(self) -> None:
        """Load the chosen state and explain its decision."""
        source = self.source.value
        try:
            if source == SOURCES[0]:
                nodes = self._current_nodes()
                if nodes is None:
                    raise ValueError("no labelling state yet")
                label = "the current labelling state"
            else:
                split = "train" if source == SOURCES[1] else "test"
                number = whole_number(self.index.value, "a task number")
                nodes = self._start_nodes(split, number)
                label = f"{split} task {number}"
            view = self.inspector.load(nodes, label)
        except Exception as exc:
            self.error.content = f"**cannot inspect**: {exc}"
            return
        self.error.content = ""
        self._after_load(view)

    def _after_load(self, view: InspectView) -> None:
        self.search_button.disabled = view.choices.greedy is None
        self.search_bar.visible = False
        self.search_status.content = ""
        self.tree.content = ""
        self.draw_state(view)  # first: the 3D view shows what is inspected at once
        keys = self.inspector.res.library.keys
        options = tuple(keys[r.demo_index] for r in view.ranking)
        self._keys_to_index = {keys[r.demo_index]: r.demo_index for r in view.ranking}
        self.cand_a.options = options or ("-",)
        self.cand_b.options = options or ("-",)
        if len(options) > 1:
            self.cand_b.value = options[1]  # type: ignore[misc]
        self.show(view)
        self.show_candidates()

    def inspect_nodes(self, nodes_k3: np.ndarray, label: str) -> None:
        """Explain the decision on a given rope (e.g. a step of a played-back episode)."""
        try:
            view = self.inspector.load(nodes_k3, label)
        except Exception as exc:
            self.error.content = f"**cannot inspect**: {exc}"
            self.client.add_notification("cannot inspect", str(exc), color="red")
            return
        self.error.content = ""
        self._after_load(view)
        # viser cannot switch a tab group's tab from the server: the labeller is told where.
        self.client.add_notification(
            "opened in Inspect",
            f"{label}: the Inspect tab shows it",
            auto_close_seconds=6.0,
            color="blue",
        )

    def open_pair(self, view: InspectView, demo_a: str, demo_b: str) -> None:
        """Show a loaded state with two given demos as candidates A and B (e.g. two experts')."""
        self._after_load(view)
        keys = self.inspector.res.library.keys
        for key in (demo_a, demo_b):
            if key not in self._keys_to_index and key in keys:
                self._keys_to_index[key] = keys.index(key)
        options = tuple(self._keys_to_index)
        self.cand_a.options = options
        self.cand_b.options = options
        self.cand_a.value = demo_a  # type: ignore[misc]
        self.cand_b.value = demo_b  # type: ignore[misc]
        self.show_candidates()

    def run_compare(self) -> None:
        """Candidate A in the agent's model and in the chosen world, side by side."""
        picked = self._picked()
        if self.inspector.view is None or not picked:
            self.compare_result.content = "Inspect a state and pick candidate A first."
            return
        setting = str(self.compare_world.value)
        self.compare_result.content = f"simulating A in the model and in {setting}..."
        self.compare_button.disabled = True
        try:
            out = self.inspector.model_and_world(picked[0], setting)
        except Exception as exc:  # shown as a sentence, never a raw traceback
            self.compare_result.content = f"**cannot simulate**: {exc}"
            return
        finally:
            self.compare_button.disabled = False
        names = self.inspector.res.task.stage_names

        def cell(o: ActionOutcome) -> str:
            stage = names[o.stage] if 0 <= o.stage < len(names) else str(o.stage)
            failed = f", failed: {o.failure}" if o.failure else ""
            return f"{stage}{' (knot)' if o.knot else ''}{failed}"

        codes = f"`{out.model.gauss_code or '-'}` | `{out.world.gauss_code or '-'}`"
        apart = out.apart_mm
        self.compare_result.content = "\n".join(
            [
                f"**`{self.inspector.res.library.keys[picked[0]]}`** from this rope:",
                "",
                f"| | the agent's model | {setting} |",
                "|---|---|---|",
                f"| stage reached | {cell(out.model)} | {cell(out.world)} |",
                f"| crossing code | {codes} |",
                "",
                f"The ropes end **{apart:.0f} mm** apart on average"
                + ("; the same outcome." if out.agree else "; **the outcomes differ**."),
                "",
                f"{_swatch(MODEL_AFTER)} after, in the model; {_swatch(WORLD_AFTER)} after, in "
                f"{setting}",
            ]
        )
        self.draw_compare(out.model.nodes_after_k3, out.world.nodes_after_k3)

    def draw_compare(self, model_k3: np.ndarray, world_k3: np.ndarray) -> None:
        """The rope after candidate A in the model and in the other world, over the state."""
        scene = self.client.scene
        points = [np.asarray(self.inspector.view.nodes_k3)] if self.inspector.view else []
        with self._drawing() as on, self.client.atomic():
            if not on:
                return
            for name, nodes, colour in (
                ("model", model_k3, MODEL_AFTER),
                ("world", world_k3, WORLD_AFTER),
            ):
                nodes = np.asarray(nodes, dtype=float)
                if not np.all(np.isfinite(nodes)):
                    scene.remove_by_name(f"/inspect/compare/{name}")
                    continue
                scene.add_mesh_simple(
                    f"/inspect/compare/{name}",
                    tube_vertices(nodes, 0.7 * ROPE_RADIUS),
                    tube_faces(len(nodes), 12),
                    color=colour,
                    opacity=0.85,
                )
                points.append(nodes)
            if points:
                self._frame(np.concatenate(points))

    def run_search(self) -> None:
        """Start the lookahead search: an anytime search, its choice shown after each level
        (the greedy one until then), which a person may keep before the end, or cancel."""
        if not self.inspector.start_lookahead(2, 5, self._on_search):
            self.search_status.content = "a search is running already (or no model to search with)"
            return
        self._shown_level = 0
        self.search_bar.value = 0.0  # type: ignore[misc]
        self.search_bar.visible = True
        self.search_status.content = "searching, level 1 of 2: 0 expansions so far"
        self.keep_search_button.disabled = True
        self.keep_search_button.visible = True
        self.cancel_search_button.visible = True
        self.search_button.disabled = True
        if self.inspector.view is not None:
            self.show(self.inspector.view)

    def cancel_search(self) -> None:
        """Stop the running search (it ends at its next expansion; nothing of it is kept)."""
        if self.inspector.cancel_lookahead():
            self.search_status.content = "cancelling the search..."

    def keep_search(self) -> None:
        """Stop the running search and keep the choice of the levels it finished."""
        if self.inspector.cancel_lookahead(keep=True):
            self.search_status.content = "stopping the search, keeping its choice so far..."

    def _on_search(self, view: InspectView) -> None:
        self.search_bar.value = 100.0 * view.search_progress  # type: ignore[misc]
        done, levels = view.choices.lookahead_levels or (0, view.search_levels)
        if view.search_progress < 1.0:
            status = (
                f"searching, level {min(done + 1, levels)} of {levels}: "
                f"{view.search_expansions} expansions so far"
            )
            if done:
                status += f"; choice after level {done} shown above"
            self.search_status.content = status
            self.keep_search_button.disabled = done == 0
            if done != self._shown_level:  # a level finished: its choice and tree at once
                self._shown_level = done
                self.show(view)
            return
        self.search_bar.visible = False
        self.cancel_search_button.visible = False
        self.keep_search_button.visible = False
        self.search_button.disabled = view.choices.greedy is None
        if view.search_cancelled:
            self.search_status.content = "search cancelled: nothing of it is shown"
        elif view.choices.lookahead_levels is not None:
            self.search_status.content = (
                f"search stopped after level {done} of {levels}: its choice is kept"
            )
        else:
            self.search_status.content = ""
        self.show(view)

    # ------------------------------------------------------------------ drawing
    def show(self, view: InspectView) -> None:
        """The three policies' choices, the lookahead tree and the candidate table."""
        keys = self.inspector.res.library.keys
        c = view.choices

        def name(a: int | None) -> str:
            return "-" if a is None else f"`{keys[a]}`"

        la = name(c.lookahead) if c.lookahead is not None else "(not run yet)"
        if c.lookahead_levels is not None:
            done, levels = c.lookahead_levels
            searching = view.search_progress < 1.0
            if c.lookahead is None:
                la = f"(searching level 1 of {levels}...)" if searching else "(not run yet)"
            else:
                la += f" after level {done} of {levels}" + (", searching on" if searching else "")
        if view.search_error:
            la = f"failed: {view.search_error}"
        final = c.lookahead is not None and c.lookahead_levels is None
        verdict = "all agree" if c.agree() and final else ""
        self.choices.content = (
            f"**{view.label}**, ranked by {view.model}  \n"
            f"| policy | chooses |\n|---|---|\n| nearest neighbour | {name(c.nn)} |\n"
            f"| greedy Q | {name(c.greedy)} |\n| lookahead(2, 5) | {la} |\n\n{verdict}"
        )
        info = c.lookahead_info
        if info:
            rows = lookahead_tree(info, keys)
            lines = [
                f"search: {info.get('expansions', 0)} expansions "
                f"({info.get('reused_expansions', 0)} reused) in "
                f"{info.get('wall_s', 0):.1f} s; knot found: "
                f"**{'yes' if info.get('goal_found') else 'no'}**",
                "",
                "| root candidate | depth reached | backed-up value |",
                "|---|---|---|",
            ]
            lines += [f"| `{k}` | {d} | {v:.2f} |" for k, d, v in rows]
            tree = search_tree_lines(info, keys, stage_names=self.inspector.res.task.stage_names)
            if tree:
                lines += ["", "**The search tree** (children under their parent, in search order):"]
                lines += ["", *tree]
            self.tree.content = "\n".join(lines)
        table = [
            "| rank | demo | Q | cost | NN rank |",
            "|---|---|---|---|---|",
        ]
        for r in view.ranking:
            q = "-" if r.q is None else f"{r.q:.2f}"
            nn = view.nn_rank_of.get(r.demo_index, "-")
            table.append(f"| {r.rank} | `{r.demo_key}` | {q} | {r.nn_cost:.3f} | {nn} |")
        self.table.content = "\n".join(table)

    def _picked(self) -> list[int]:
        out = []
        for dd in (self.cand_a, self.cand_b):
            a = self._keys_to_index.get(dd.value)
            if a is not None and a not in out:
                out.append(a)
        return out

    def show_candidates(self) -> None:
        """Bar plot of A's (and B's) contributions, and their costs side by side."""
        view = self.inspector.view
        picked = self._picked()
        if view is None or not picked:
            return
        keys = self.inspector.res.library.keys
        if view.contributions:
            self.plot.image = contribution_plot(view, picked, keys)
        regs = [self.inspector.registration(a) for a in picked]
        names = ["map_fwd", "map_bwd", "bend_f", "bend_g", "residual_fwd_m", "residual_bwd_m"]
        head = "| cost part | " + " | ".join(f"`{r.demo_key}`" for r in regs) + " |"
        rows = [
            "**Registration costs** of A and B onto this rope (not Q: lower fits better)",
            "",
            head,
            "|---" * (len(regs) + 1) + "|",
        ]
        for n in names:
            rows.append(
                f"| {n} | " + " | ".join(f"{r.costs.get(n, np.nan):.4f}" for r in regs) + " |"
            )
        self.compare.content = "\n".join(rows)
        self.draw_3d()

    def draw_state(self, view: InspectView) -> None:
        """Draw the inspected rope and its cloud in place of the labelling view, framed."""
        nodes = np.asarray(view.nodes_k3)
        self.compare_result.content = ""
        with self._drawing(enter=True), self.client.atomic():
            self.client.scene.remove_by_name("/inspect/compare")
            self.client.scene.add_mesh_simple(
                "/inspect/rope",
                tube_vertices(nodes, ROPE_RADIUS),
                tube_faces(len(nodes), 12),
                color=ROPE_COLOUR,
            )
            self.client.scene.add_point_cloud(
                "/inspect/scene_cloud",
                np.asarray(view.cloud_n3, np.float32),
                SCENE_CLOUD,
                point_size=0.008,
                point_shape="circle",
                precision="float32",
            )
            self._frame(np.concatenate([nodes, np.asarray(view.cloud_n3)]))

    def draw_3d(self, *, reframe: bool = False) -> None:
        """Draw (or hide) candidate A's registration over the inspected state; ``reframe``
        points the camera at all of it. Nothing is drawn once the user has left Inspect's view."""
        on = bool(self.show_3d.value)
        self.legend.visible = on
        view = self.inspector.view
        picked = self._picked()
        # The registration is computed outside the scene's lock (it can take a while).
        reg = self.inspector.registration(picked[0]) if view is not None and picked and on else None
        with self._drawing() as showing:
            if showing:
                self._draw_3d(reframe=reframe, registration=reg)

    def _draw_3d(self, *, reframe: bool, registration: RegistrationView | None) -> None:
        scene = self.client.scene
        scene.remove_by_name("/inspect/registration")
        view = self.inspector.view
        if view is None or not self._picked():
            return
        nodes = np.asarray(view.nodes_k3)
        # The rope half see-through while the registration is shown: the clouds lie on it.
        scene.add_mesh_simple(
            "/inspect/rope",
            tube_vertices(nodes, ROPE_RADIUS),
            tube_faces(len(nodes), 12),
            color=ROPE_COLOUR,
            opacity=0.5 if registration is not None else 1.0,
        )
        if registration is None:
            if reframe:
                self._frame(np.concatenate([nodes, np.asarray(view.cloud_n3)]))
            return
        reg = registration
        with self.client.atomic():
            scene.add_point_cloud(
                "/inspect/registration/demo_cloud",
                np.asarray(reg.demo_cloud_n3, np.float32),
                DEMO_CLOUD,
                point_size=0.007,
                precision="float32",
            )
            scene.add_point_cloud(
                "/inspect/registration/warped",
                np.asarray(reg.warped_n3, np.float32),
                WARPED_CLOUD,
                point_size=0.009,
                point_shape="diamond",
                precision="float32",
            )
            scene.add_line_segments(
                "/inspect/registration/correspondence",
                np.asarray(reg.pairs_n23, np.float32),
                PAIR_COLOUR,
                thickness=1.5,
                thickness_units="screen",
            )
        if reframe:
            self._frame(np.concatenate([nodes, reg.demo_cloud_n3, reg.warped_n3]))
