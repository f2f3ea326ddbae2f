"""`jaxrt view SCENE`: an interactive window with sliders for material, model, light and camera.

    from jaxrt.viewer import Viewer
    v = Viewer("spheres", object="phong", width=64, height=48)
    v.set_param("s", 200.0); v.set_model("ward"); v.set_light(position=[2, 5, 3]); v.orbit(30, 20)
    v.image            # (H, W, 3) linear RGB of the current state
    fig = v.figure()   # matplotlib figure with the widgets (any backend; Agg for headless use)

The selected object gets one material per registered model (`jaxrt.sweep.substitute`), each starting
from the object's own material where parameter names agree, so a model switch is a value change
(which material the object's faces wear) just like a parameter, light or camera change: the scene
structure never changes and every update re-runs the one compiled `jaxrt.frame`. Slider
ranges and log/linear scales come from each model's `Param` declarations (a measured material,
`model = "measured"` in the scene, is one more choice when the object wears one: its model,
"nbrdf" or "merl", has no parameters, so it has no sliders but δ's); a log-scale parameter's
slider moves over log10(value) and its label shows the value itself. RGB parameters get one slider
per channel (`rho_d.r`, `rho_d.g`, `rho_d.b`), so moving one keeps the material's colour.

Path-traced scenes (`[render] integrator = "path"`, or `integrator="path"` / `jaxrt view --integrator
path`) render progressively: every change starts a new `jaxrt.integrators.path.Accumulation` with pass 0, each
`refine()` (called by the window's idle timer) adds the next pass through the one compiled
`jaxrt.integrators.path.samples_jit`, and `image` is the running mean, sum/count. The title shows the count.
Photon-mapped scenes (`integrator = "sppm"`) refine the same way through `jaxrt.integrators.sppm.steps`: the
first `refine()` after a change runs one pass, later ones as many as the last call's time per pass fits in
VIEW_CALL_SECONDS (`jaxrt.integrators.sppm.passes_per_call`; a small frame's pass takes milliseconds on a GPU).

On several devices (`devices=`, `jaxrt view --devices N`, as `jaxrt render`) a frame is split into the
tiles `jaxrt render` would use (`jaxrt.render_tiles.plan`, planned once: the scene's shapes never
change), a Whitted frame through `jaxrt.render_tiles.render` and each progressive path pass through
`jaxrt.render_tiles.accumulate` (the first two passes after a change time the tiles, the later ones
assign them by cost), so a frame equals `jaxrt.render(..., devices=N)`'s. SPPM passes stay on the default
device (a photon pass is one whole-frame program).
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from typing import Any

import numpy as np
from jaxtyping import Float

import brdfs
from jaxrt import sweep as _sweep
from jaxrt.errors import InputError

MAX_SAMPLES = 1 << 16  # the idle timer stops refining here (samples per pixel)
VIEW_CALL_SECONDS = 0.1  # an SPPM refine() runs the passes that fit in this (a slider answers within it)


def orbit_position(look_at, distance: float, azimuth: float, elevation: float) -> np.ndarray:
    """Camera position on a sphere about `look_at` (y up): azimuth [deg] from +z towards +x,
    elevation [deg] above the horizontal plane; (3,) float32."""
    az, el = math.radians(azimuth), math.radians(elevation)
    d = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
    return (np.asarray(look_at, np.float64) + distance * d).astype(np.float32)


def orbit_angles(position, look_at) -> tuple[float, float, float]:
    """Inverse of `orbit_position`: (distance, azimuth [deg], elevation [deg])."""
    d = np.asarray(position, np.float64) - np.asarray(look_at, np.float64)
    r = float(np.linalg.norm(d))
    return r, math.degrees(math.atan2(d[0], d[2])), math.degrees(math.asin(np.clip(d[1] / r, -1.0, 1.0)))


def slider_spec(p) -> tuple[float, float, float]:
    """(min, max, initial) of a parameter's slider in slider units: log10 for log-scale parameters."""
    if p.scale == "log":
        return math.log10(p.lo), math.log10(p.hi), math.log10(p.default)
    return p.lo, p.hi, p.default


def from_slider(p, x: float) -> float:
    """A slider position back to the parameter value (clipped to the declared range)."""
    v = 10.0 ** x if p.scale == "log" else x
    return float(min(max(v, p.lo), p.hi))


class Viewer:
    """Rendering state of the interactive viewer: a scene, a selected object, its model and parameters.

    Args:
        scene: a scene file path or shipped name.
        object: the object whose material the sliders edit (default: the first non-plane object).
        width, height: render size [pixels] (default: the scene file's).
        exposure: display exposure [stops].
        frame: point the camera at the object, zoomed to fit it (`jaxrt.sweep.frame_object`); the
            orbit then turns about the object's centre.
        integrator: "whitted" or "path" (default: the scene file's); spp: samples per pixel of one
            pass (default: the scene file's).
        devices: None (default): the default device alone; else the devices to split each frame over,
            as `jaxrt.render`'s `devices` ("all", a number N: the first N, or a list of devices).
    Attributes:
        image: (H, W, 3) float32 linear RGB of the current state; frame_time: seconds of the last
            render (of the last pass when progressive).
        model: current model name; models: the names the object can switch between (the analytic
            models, then its own measured model if it wears one); values: {param: value} of the
            current model (RGB as the channel mean); channels: {RGB param: [r, g, b]}.
        progressive: True for a path-traced scene; accumulation: its `jaxrt.integrators.path.Accumulation`
            (None otherwise); samples: samples per pixel in `image` (settings.spp for Whitted).
    """

    def __init__(self, scene: str | os.PathLike, object: str | None = None, width: int | None = None,
                 height: int | None = None, exposure: float = 0.0, frame: bool = False,
                 integrator: str | None = None, spp: int | None = None, confine: bool | None = None,
                 devices: Any = None, devices_source: str = "devices="):
        from jaxrt import scene as _scene
        from jaxrt.image import check_exposure

        check_exposure(exposure)
        self._devices = None
        if devices is not None:
            from jaxrt import _devices

            chosen = _devices.select(devices, devices_source)
            self._devices = chosen if _devices.sharded(chosen) else None
        spec = _scene.parse(_scene.find_scene(scene), overrides={
            "camera.width": width, "camera.height": height, "render.integrator": integrator, "render.spp": spp},
            confine=confine)
        spec, self.object, self.model = _sweep.substitute(spec, None, object, inherit=True)
        self.models = brdfs.names() + ((self.model,) if brdfs.is_measured(self.model) else ())
        self.scene = _scene.build(spec)
        if frame:
            self.scene = _sweep.frame_object(self.scene, self.object)
        self.exposure = float(exposure)
        cam = self.scene.camera
        self._look_at = np.asarray(cam.look_at, np.float64)
        self.distance, self.azimuth, self.elevation = orbit_angles(np.asarray(cam.position), self._look_at)
        self._fig = None
        self.sliders: dict[str, Any] = {}
        self.frame_time = float("nan")
        self._pass_seconds = float("nan")  # seconds per progressive pass of the last refine()
        self._timer = None
        self.progressive = self.scene.settings.integrator in ("path", "sppm")
        self.accumulation = None
        self._plan = None
        if self._devices is not None and self.scene.settings.integrator == "sppm":
            self._devices = None  # a photon pass runs on the default device (`jaxrt.render_tiles.render`)
        if self._devices is not None:
            from jaxrt import _devices, render_tiles

            self._plan = render_tiles.plan(self.scene, devices=self._devices, devices_source=devices_source)
            if not self.progressive:  # compiled and measured once, as `render_tiles.render` would every frame
                self._plan = render_tiles.compile_plan(_devices.replicate(self.scene, self._devices), self._plan)
        self.render()

    # ---- state -------------------------------------------------------------------------------
    @property
    def spec(self) -> tuple:
        """The current model's `Param`s plus `jaxrt.sweep.DELTA` for non-delta models."""
        m = brdfs.get(self.model)
        return m.spec + (() if m.delta else (_sweep.DELTA,))

    @property
    def values(self) -> dict[str, float]:
        mats = self.scene.materials
        i = mats.index(_sweep.material_name(self.model))
        table, row = mats.params[int(mats.model_id[i])], int(mats.row[i])
        names = brdfs.get(self.model).param_names  # a measured model's table holds data, not parameters
        out = {k: float(np.mean(np.asarray(v[row]))) for k, v in table.items() if k in names}
        if not brdfs.get(self.model).delta:
            out["delta"] = float(mats.delta[i])
        return out

    @property
    def channels(self) -> dict[str, list[float]]:
        """{RGB parameter: [r, g, b]} of the current model."""
        mats = self.scene.materials
        i = mats.index(_sweep.material_name(self.model))
        table, row = mats.params[int(mats.model_id[i])], int(mats.row[i])
        rgb = {p.name for p in brdfs.get(self.model).spec if p.rgb}
        return {k: [float(x) for x in np.asarray(v[row]).reshape(-1)] for k, v in table.items() if k in rgb}

    @property
    def compiles(self) -> int:
        """Number of compiled variants (process-wide) of the function this viewer renders with:
        `jaxrt.frame`, or the pass `jaxrt.integrators.path.samples_jit` when progressive."""
        from jaxrt.integrators import path as _path
        from jaxrt import integrators as _render

        if self.scene.settings.integrator == "sppm":
            return _render.sppm.steps._cache_size()
        return (_path.samples_jit if self.progressive else _render.frame)._cache_size()

    @property
    def samples(self) -> int:
        if self.accumulation is None:
            return self.scene.settings.spp
        if self.scene.settings.integrator == "sppm":  # one camera sample per pixel and pass
            return int(self.accumulation.passes)
        return int(self.accumulation.count)

    def render(self) -> Float[np.ndarray, "H W 3"]:
        """Re-render the current state with the compiled frame; sets `image` and `frame_time`.
        Progressive: drop the accumulation and start again from pass 0 (one pass)."""
        from jaxrt import integrators as _render

        if self.progressive:
            self.accumulation = None
            if self._plan is not None:  # time the tiles again: the change may move their costs
                self._plan = dataclasses.replace(self._plan, costs=None, timed=0)
            return self.refine()
        t0 = time.perf_counter()
        if self._plan is not None:
            from jaxrt import render_tiles

            img = render_tiles.render(self.scene, use_plan=self._plan)
        else:
            img = _render.frame(self.scene)
            img.block_until_ready()
        self.frame_time = time.perf_counter() - t0
        self._show(img)
        return self.image

    def refine(self) -> Float[np.ndarray, "H W 3"]:
        """Add the next pass (settings.spp samples per pixel, pass index = passes so far) to the
        accumulation and show the running mean (SPPM: `sppm.passes_per_call` passes, one the first
        time after a change); a Whitted viewer's image is final, so it returns it unchanged. The pass
        index (and SPPM's pass count) is traced: no pass recompiles."""
        from jaxrt.integrators import path as _path
        from jaxrt.integrators import sppm as _sppm

        if not self.progressive:
            return self.image
        t0 = time.perf_counter()
        count = 1
        if self._plan is not None:
            from jaxrt import render_tiles

            acc, self._plan = render_tiles.accumulate(self.scene, self.accumulation, use_plan=self._plan,
                                                      return_plan=True)
        elif self.scene.settings.integrator == "sppm":
            if self.accumulation is not None:
                count = _sppm.passes_per_call(self._pass_seconds, max(MAX_SAMPLES - self.samples, 1),
                                              VIEW_CALL_SECONDS)
            acc = _sppm.accumulate(self.scene, self.accumulation, count)
        else:
            acc = _path.accumulate(self.scene, self.accumulation)
        img = acc.image
        img.block_until_ready()
        self.frame_time = time.perf_counter() - t0
        self._pass_seconds = self.frame_time / count
        self.accumulation = acc
        self._show(img)
        return self.image

    def _show(self, img) -> None:
        from jaxrt import _devices  # (the viewer's module imports no JAX until a frame is made)

        self.image = np.nan_to_num(_devices.to_host(img), nan=0.0, posinf=0.0, neginf=0.0)
        self._refresh()

    def set_param(self, name: str, value: float, channel: int | None = None) -> None:
        """Set a parameter of the current model (or "delta") and re-render; InputError if out of range.
        `channel` (0, 1, 2) sets one channel of an RGB parameter and keeps the other two."""
        p = _sweep.param_spec(self.model, name)
        if channel is None:
            new: float | list[float] = float(value)
        else:
            if not p.rgb or channel not in (0, 1, 2):
                raise InputError(f"{self.model}.{name}: channel {channel!r} needs an RGB parameter and 0, 1 or 2")
            new = list(self.channels[name])
            new[channel] = float(value)
        self.scene = self.scene.with_material(_sweep.material_name(self.model), **{name: new})
        self.render()

    def set_model(self, name: str) -> None:
        """Dress the object in model `name` (one of `models`; its own material, kept between switches)
        and re-render."""
        if name not in self.models:
            raise InputError(f"model {name!r}: the object can wear {', '.join(self.models)}")
        self.model = name
        self.scene = _sweep.use_model(self.scene, self.object, name)
        self._rebuild_param_sliders()
        self.render()

    def set_light(self, position=None, intensity=None, index: int = 0) -> None:
        """Move / re-scale point light `index` (position (3,) scene units, intensity W/sr, scalar or RGB)."""
        if not 0 <= index < self.scene.lights.count:
            raise InputError(f"light index {index}: the scene has {self.scene.lights.count} light(s)")
        self.scene = self.scene.with_light(index, position=position, intensity=intensity)
        self.render()

    def orbit(self, azimuth: float, elevation: float) -> None:
        """Place the camera at azimuth/elevation [deg] about its look-at point (same distance)."""
        for k, v, lim in (("azimuth", azimuth, 360.0), ("elevation", elevation, 89.0)):
            if not math.isfinite(v) or abs(v) > lim:
                raise InputError(f"{k}: expected a number in [-{lim:g}, {lim:g}] degrees, got {v!r}")
        self.azimuth, self.elevation = float(azimuth), float(elevation)
        pos = orbit_position(self._look_at, self.distance, self.azimuth, self.elevation)
        self.scene = self.scene.with_camera(position=pos, up=np.array([0.0, 1.0, 0.0], np.float32))
        self.render()

    def srgb(self) -> np.ndarray:
        """The current image as 8-bit sRGB (H, W, 3)."""
        from jaxrt.image import to_srgb8

        return to_srgb8(self.image, self.exposure)

    def png(self) -> bytes:
        """The current image as PNG bytes (sRGB), e.g. for an ipywidgets.Image."""
        import io

        from PIL import Image

        buf = io.BytesIO()
        Image.fromarray(self.srgb(), mode="RGB").save(buf, format="PNG")
        return buf.getvalue()

    def status(self) -> str:
        s = f"{self.object}: {self.model}   frame {1e3 * self.frame_time:.1f} ms"
        if self.progressive:
            s += f"   {self.samples} spp"
        return s

    # ---- matplotlib window -------------------------------------------------------------------
    def figure(self):
        """Build (once) and return the matplotlib figure with the image and its widgets.

        `sliders` maps parameter names (and light_x/y/z, intensity, azimuth, elevation) to
        `matplotlib.widgets.Slider`s and "model" to the `RadioButtons`; their callbacks call the
        methods above, so `slider.set_val(x)` drives the viewer exactly like a mouse drag.
        """
        if self._fig is not None:
            return self._fig
        import matplotlib.pyplot as plt
        from matplotlib.widgets import RadioButtons, Slider

        fig = plt.figure(figsize=(10, 6))
        self._fig = fig
        self._ax = fig.add_axes((0.02, 0.08, 0.56, 0.86))
        # a framed image on a grey page: a white furnace or a white background stays visible as an image
        fig.set_facecolor("0.82")
        self._ax.set_xticks([])
        self._ax.set_yticks([])
        for spine in self._ax.spines.values():
            spine.set_edgecolor("0.25")
            spine.set_linewidth(1.2)
        self._im = self._ax.imshow(self.srgb(), interpolation="nearest")
        self._title = self._ax.set_title(self.status(), fontsize=9)
        names = self.models
        rax = fig.add_axes((0.62, 0.70, 0.14, 0.26))
        radio = RadioButtons(rax, names, active=names.index(self.model))
        radio.on_clicked(self.set_model)
        self.sliders["model"] = radio
        # light and camera sliders (bottom right); ranges from the scene's own extent. A scene lit
        # only by emitters or an environment (path-traced scenes often are) has no light sliders.
        rows = []
        if self.scene.lights.count > 0:
            pos = np.asarray(self.scene.lights.position[0], np.float64)
            inten = float(np.mean(np.asarray(self.scene.lights.intensity[0])))
            reach = max(float(np.max(np.abs(pos))), self.distance, 1.0) * 2.0
            rows = [
                ("light_x", -reach, reach, pos[0], lambda v: self._light_axis(0, v)),
                ("light_y", -reach, reach, pos[1], lambda v: self._light_axis(1, v)),
                ("light_z", -reach, reach, pos[2], lambda v: self._light_axis(2, v)),
                ("intensity", 0.0, max(4.0 * inten, 1.0), inten, lambda v: self.set_light(intensity=v)),
            ]
        rows += [
            ("azimuth", -180.0, 180.0, self.azimuth, lambda v: self.orbit(v, self.elevation)),
            ("elevation", -89.0, 89.0, self.elevation, lambda v: self.orbit(self.azimuth, v)),
        ]
        for k, (name, lo, hi, init, cb) in enumerate(rows):
            ax = fig.add_axes((0.68, 0.05 + 0.045 * k, 0.22, 0.03))
            s = Slider(ax, name, lo, hi, valinit=float(np.clip(init, lo, hi)))
            s.on_changed(cb)
            self.sliders[name] = s
        self._param_axes: list = []
        self._rebuild_param_sliders()
        if self.progressive:
            # a 1 ms timer runs between GUI events, so each tick adds one pass while the user is
            # idle; a change resets the accumulation through render(). Agg's timer never fires.
            self._timer = fig.canvas.new_timer(interval=1)
            self._timer.add_callback(self._tick)
            self._timer.start()
        return fig

    def _tick(self) -> None:
        if self.samples < MAX_SAMPLES:
            self.refine()

    def _light_axis(self, axis: int, value: float) -> None:
        pos = np.asarray(self.scene.lights.position[0], np.float64).copy()
        pos[axis] = value
        self.set_light(position=pos)

    def _rebuild_param_sliders(self) -> None:
        if self._fig is None:
            return
        from matplotlib.widgets import Slider

        for ax in self._param_axes:
            ax.remove()
        for p in list(self.sliders):
            if p not in ("model", "light_x", "light_y", "light_z", "intensity", "azimuth", "elevation"):
                del self.sliders[p]
        self._param_axes = []
        vals, chans = self.values, self.channels
        rows = []  # (slider name, Param, channel or None, value)
        for p in self.spec:
            if p.rgb and p.name in chans:
                rows += [(f"{p.name}.{c}", p, k, chans[p.name][k]) for k, c in enumerate("rgb")]
            else:
                rows.append((p.name, p, None, vals[p.name]))
        # the stack runs down from 0.62 and stays above the light and camera sliders (top at ~0.32)
        step = min(0.045, 0.30 / max(len(rows), 1))
        for k, (label, p, channel, value) in enumerate(rows):
            lo, hi, _ = slider_spec(p)
            x = math.log10(max(value, p.lo)) if p.scale == "log" else value
            ax = self._fig.add_axes((0.68, 0.62 - step * k, 0.22, min(0.03, 0.7 * step)))
            s = Slider(ax, label, lo, hi, valinit=float(np.clip(x, lo, hi)))
            s.valtext.set_text(f"{from_slider(p, s.val):.3g}")

            def changed(x, p=p, s=s, channel=channel):
                s.valtext.set_text(f"{from_slider(p, x):.3g}")
                self.set_param(p.name, from_slider(p, x), channel)

            s.on_changed(changed)
            self.sliders[label] = s
            self._param_axes.append(ax)
        self._fig.canvas.draw_idle()

    def _refresh(self) -> None:
        if self._fig is None:
            return
        self._im.set_data(self.srgb())
        self._title.set_text(self.status())
        self._fig.canvas.draw_idle()


def notebook_controls(viewer: Viewer, scale: int = 2):
    """ipywidgets controls for a `Viewer` (the notebook twin of `Viewer.figure`).

    Returns (box, sliders): a widget to `display`, and name -> widget for every control: the current
    model's parameters (FloatLogSlider for log-scale `Param`s, FloatSlider otherwise, ranges from the
    declarations; δ for non-delta models), "model" (Dropdown), light_x/y/z, intensity, azimuth,
    elevation. Changing a control's `.value` calls the viewer and refreshes the image and the frame
    time; like the matplotlib window it never recompiles. `scale` magnifies the displayed image.
    """
    import ipywidgets as w

    h, wd = viewer.image.shape[:2]
    image = w.Image(value=viewer.png(), format="png", width=scale * wd, height=scale * h)
    status = w.Label(viewer.status())
    sliders: dict = {}
    params = w.VBox()

    def refresh():
        image.value = viewer.png()
        status.value = viewer.status()

    def on(name, fn):
        sliders[name].observe(lambda ch: (fn(ch["new"]), refresh()), names="value")

    def build_params():
        for k in [k for k in sliders if k in _param_names(sliders)]:
            del sliders[k]
        vals, chans, rows = viewer.values, viewer.channels, []
        for p in viewer.spec:
            entries = ([(f"{p.name}.{c}", k, chans[p.name][k]) for k, c in enumerate("rgb")]
                       if p.rgb and p.name in chans else [(p.name, None, vals[p.name])])
            for label, channel, value in entries:
                if p.scale == "log":
                    lo, hi, _ = slider_spec(p)
                    s = w.FloatLogSlider(value=value, base=10, min=lo, max=hi, step=(hi - lo) / 200,
                                         description=label, readout_format=".3g")
                else:
                    s = w.FloatSlider(value=value, min=p.lo, max=p.hi, step=(p.hi - p.lo) / 200,
                                      description=label, readout_format=".3g")
                s.tooltip = p.doc
                sliders[label] = s
                on(label, lambda v, n=p.name, c=channel: viewer.set_param(n, v, c))
                rows.append(s)
        params.children = rows

    def _param_names(d):
        return set(d) - {"model", "light_x", "light_y", "light_z", "intensity", "azimuth", "elevation"}

    sliders["model"] = w.Dropdown(options=list(viewer.models), value=viewer.model, description="model")

    def set_model(name):
        viewer.set_model(name)
        build_params()

    on("model", set_model)
    lit = viewer.scene.lights.count > 0  # no light widgets for a scene lit by emitters/environment only
    if lit:
        pos = np.asarray(viewer.scene.lights.position[0], np.float64)
        inten = float(np.mean(np.asarray(viewer.scene.lights.intensity[0])))
        reach = max(float(np.max(np.abs(pos))), viewer.distance, 1.0) * 2.0
        for k, axis in enumerate("xyz"):
            sliders[f"light_{axis}"] = w.FloatSlider(value=pos[k], min=-reach, max=reach, step=reach / 100,
                                                     description=f"light {axis}")

            def move(v, k=k):
                q = np.asarray(viewer.scene.lights.position[0], np.float64).copy()
                q[k] = v
                viewer.set_light(position=q)

            on(f"light_{axis}", move)
        sliders["intensity"] = w.FloatSlider(value=inten, min=0.0, max=max(4 * inten, 1.0),
                                             description="intensity")
        on("intensity", lambda v: viewer.set_light(intensity=v))
    sliders["azimuth"] = w.FloatSlider(value=viewer.azimuth, min=-180, max=180, description="azimuth")
    on("azimuth", lambda v: viewer.orbit(v, viewer.elevation))
    sliders["elevation"] = w.FloatSlider(value=viewer.elevation, min=-89, max=89, description="elevation")
    on("elevation", lambda v: viewer.orbit(viewer.azimuth, v))
    build_params()
    fixed = w.VBox([sliders[k] for k in ("light_x", "light_y", "light_z", "intensity", "azimuth", "elevation")
                    if k in sliders])
    box = w.HBox([w.VBox([image, status]), w.VBox([sliders["model"], params, fixed])])
    return box, sliders
