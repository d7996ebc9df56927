"""The ``respa`` command: safe outer steps of an impulse (r-RESPA) integrator."""

from __future__ import annotations

import dataclasses
from typing import Any

import click

from stepsafe.api.md import impulse, impulse_advice, impulse_method
from stepsafe.cli.group import (
    DURATION,
    EXIT_UNSAFE,
    FLOAT,
    INT,
    TIME_UNIT_NAMES,
    _input_error,
    _option_value,
    criterion_option,
    main,
)
from stepsafe.cli.plots import plot_format, pyplot, save_figure
from stepsafe.cli.report import fmt, fmt_below, print_json
from stepsafe.core.impulse import stability_chart
from stepsafe.core.regions import find_region
from stepsafe.core.resonances import rotations
from stepsafe.units import implied_time_unit, quantity


def _frequency(beta, wavenumber, which: str, unit) -> float:
    given = [v for v in (beta, wavenumber) if v is not None]
    if len(given) != 1:
        raise _input_error(f"give the {which} frequency once: --{which}-beta B or "
                           f"--{which}-wavenumber K")
    if beta is not None:
        return beta
    return _option_value(lambda v: quantity(v, "wavenumber", unit), f"{which}-wavenumber",
                         wavenumber)


@main.command("respa")
@click.argument("method", required=False, metavar="[METHOD]")
@click.option("--outer", default=None, metavar="METHOD",
              help="Splitting over the slow force (its kicks) at the outer step H "
                   "[default: verlet].")
@click.option("--inner", default=None, metavar="METHOD",
              help="Splitting over the fast force, run SUBSTEPS times per outer drift "
                   "[default: verlet].")
@click.option("--substeps", type=INT, default=None, metavar="K",
              help="Inner steps per outer drift (inner step H/K) [default: METHOD's, else 4].")
@click.option("--fast-beta", type=FLOAT, default=None, metavar="B",
              help="Angular frequency of the fast force alone (rad per time unit).")
@click.option("--slow-beta", type=FLOAT, default=None, metavar="B",
              help="Angular frequency of the slow force alone (rad per time unit).")
@click.option("--fast-wavenumber", default=None, metavar="K",
              help="The fast frequency as a wavenumber in cm^-1 (needs --time-unit).")
@click.option("--slow-wavenumber", default=None, metavar="K",
              help="The slow frequency as a wavenumber in cm^-1 (needs --time-unit).")
@click.option("--time-unit", type=click.Choice(TIME_UNIT_NAMES), default=None,
              help="Unit of H in and out (and of the frequencies' 1/time).")
@click.option("--step", "step", type=DURATION, default=None, metavar="H",
              help="Check this outer step: exit 0 if safe, 1 if not; in --time-unit, or "
                   "with a unit (2fs).")
@click.option("--zmax", type=FLOAT, default=None, metavar="Z",
              help="Search beta*H up to Z, beta = sqrt(fast^2 + slow^2) [default: just "
                   "past the inner method's own limit, Omega H = K z*_inner].")
@click.option("--resonance-order", type=INT, default=None, metavar="N",
              help="Also keep H below the outer step's first nonlinear resonance "
                   "n theta = 2 pi m of order n <= N (3: the limit near a third of the fast "
                   "period).")
@click.option("--plot", "plot_file", default=None, metavar="FILE.png",
              help="Draw the stability chart in the plane (Omega H, omega H) with the ray of "
                   "your frequency ratio (needs matplotlib).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
@criterion_option("stability")
def respa_cmd(method, outer, inner, substeps, fast_beta, slow_beta, fast_wavenumber,
              slow_wavenumber, time_unit, step, zmax, resonance_order, plot_file, as_json,
              criterion) -> None:
    """Safe outer steps of an impulse / r-RESPA multiple-time-step integrator.

    METHOD is an impulse method file (kind: impulse, e.g. respa-verlet) bringing its outer
    and inner methods and substep count; or give --outer and --inner. The test model is
    one coordinate with a fast force (frequency Omega alone) and a slow
    one (omega): the outer splitting kicks with the slow force at step H, each of its
    drifts is SUBSTEPS inner steps over the fast force. Impulse methods go unstable in
    bands just below the steps where the inner steps turn the fast vibration by j pi (near
    Omega H = j pi, half periods of the fast vibration), long before the inner
    method's own limit; the bands are listed with Omega H / pi. At a fixed ratio the outer
    step is exactly a splitting on the oscillator of frequency sqrt(Omega^2 + omega^2), so
    the analysis is that of `stepsafe advise`. The default criterion here is stability
    (|tr M| <= 2, the bands of the impulse literature); structure also requires the
    sense of rotation, which the outer step reverses beyond Omega H = pi.

    \b
    Examples:
      stepsafe respa --fast-beta 10 --slow-beta 1 --substeps 4
      stepsafe respa respa-verlet --fast-beta 10 --slow-beta 1
      stepsafe respa --fast-wavenumber 3700 --slow-wavenumber 300 --time-unit fs \\
          --substeps 4 --step 2
    """
    if method is not None and (outer is not None or inner is not None):
        raise _input_error(f"give the impulse method {method} or --outer/--inner, not both")
    impulse_obj = impulse_method(method or outer or "verlet", inner, substeps)
    time_unit = time_unit or implied_time_unit(step)  # --step 2fs names the time unit
    fast = _frequency(fast_beta, fast_wavenumber, "fast", time_unit)
    slow = _frequency(slow_beta, slow_wavenumber, "slow", time_unit)
    report = impulse(method or outer or "verlet", inner, substeps=impulse_obj.substeps,
                     fast_beta=fast, slow_beta=slow, step=step, criterion=criterion, zmax=zmax,
                     time_unit=time_unit, resonance_order=resonance_order)
    data = report.to_dict()
    if plot_file is not None:
        draw_chart(impulse_obj, slow / fast if fast > 0 else None, plot_file)
    if as_json:
        print_json(data)
    else:
        print_respa(data)
    if step is not None and not data["safe"]:
        raise SystemExit(EXIT_UNSAFE)


def print_respa(data: dict[str, Any]) -> None:
    u = f" {data['time_unit']}" if data["time_unit"] else ""
    click.echo(f"{data['method']}: fast {fmt(data['fast'])}, slow {fmt(data['slow'])} rad/"
               f"{data['time_unit'] or 'time unit'}, {data['substeps']} substep(s) per outer "
               f"drift (criterion: {data['criterion']})")
    if data["h_max"]:
        click.echo(f"Safe outer steps: 0 < H < {fmt_below(data['h_max'])}{u}"
                   f" (Omega H / pi = {data['fast'] * data['h_max'] / 3.141592653589793:.4g})")
    else:
        click.echo("No safe outer step from 0.")
    for lo, hi in data["safe_h"][1:]:
        click.echo(f"  also safe: {fmt(lo)} < H < {'the horizon' if hi is None else fmt(hi)}{u}")
    for band in data["bands"]:
        hi = "the horizon" if band["hi"] is None else f"{fmt(band['hi'])}{u}"
        phase_hi = "" if band["fast_phase_hi"] is None else f"{band['fast_phase_hi']:.4g}"
        what = {"resonance": "M = ±I within rounding (excluded)",
                "nonlinear": "beyond the nonlinear resonance asked for",
                "unstable": "unstable band"}[band["kind"]]
        click.echo(f"  {what}: {fmt(band['lo'])}{u} to {hi} "
                   f"(Omega H / pi from {band['fast_phase_lo']:.4g} to {phase_hi})")
    if data["horizon"] is not None:
        click.echo(f"Outer steps above {fmt(data['horizon'])}{u} were not analysed.")
    if data["nonlinear_resonances"]:
        click.echo("Nonlinear resonances of the outer step (n theta = 2 pi m; "
                   "--resonance-order N keeps H below those of order <= N): " + ", ".join(
                       f"{r['resonance']} at H = {fmt_below(r['h'])}{u}"
                       for r in data["nonlinear_resonances"]))
    if data["step"] is not None:
        verdict = "SAFE" if data["safe"] else "UNSAFE"
        reason = "" if data["safe"] else f": {data['reason']}"
        click.echo(f"{verdict}: H = {fmt(data['step'])}{u}{reason}")


#: Pixels per side of the stability chart.
CHART_PIXELS = 400


def draw_chart(method: Any, ratio: float | None, output: str) -> None:
    """The plane (Omega H, omega H) of the impulse method: shaded where one outer step is
    unstable (|tr M| > 2), up to 1.05 times the inner method's own limit in Omega H, with
    the ray of the frequency ratio omega / Omega when given."""
    import numpy as np

    plt = pyplot()
    fmt = plot_format(output, plt)
    k = method.substeps
    z_inner = find_region(method.inner, "oscillator", 40.0).first_boundary
    x_top = 1.05 * k * (z_inner or 10.0)
    y_top = 0.5 * x_top
    x = np.linspace(x_top / CHART_PIXELS, x_top, CHART_PIXELS)
    y = np.linspace(y_top / CHART_PIXELS, y_top, CHART_PIXELS)
    unstable = stability_chart(method, x, y) >= 1.0
    fig, ax = plt.subplots(figsize=(7, 4.5))
    ax.imshow(unstable, origin="lower", extent=(0, x_top, 0, y_top), aspect="auto",
              cmap="Greys", vmin=0, vmax=1.6, interpolation="nearest")
    if ratio is not None:
        ray = np.array([0.0, x_top])
        ax.plot(ray, ray * ratio, color="tab:red", lw=1.2, label="your ratio omega/Omega")
        ax.legend(fontsize=8, loc="upper left")
    # the inner method's half turns: K theta_in(Omega H / K) = j pi
    inner_region = find_region(method.inner, "oscillator", x_top / k)
    for r in rotations(method.inner, inner_region, [(2 * k, j) for j in range(1, k)]):
        ax.axvline(k * r.z, color="tab:blue", lw=0.6, ls=":")
    ax.set_xlim(0, x_top)
    ax.set_ylim(0, y_top)
    ax.set_xlabel("Omega H (fast)  [dotted: K inner steps turn by j pi]")
    ax.set_ylabel("omega H (slow)")
    ax.set_title(f"{method.name} with {k} substeps: unstable where shaded")
    fig.tight_layout()
    save_figure(fig, output, fmt)


def impulse_report(integrator: Any, scene_file: str | None, options: dict, *,
                   step: float | None, criterion: str, resonance_order: int | None, check: bool
                   ) -> dict[str, Any]:
    """advise or check (``step``, else the scene's h) of an impulse method on a scene."""
    return impulse_advice(integrator, scene=scene_file, substeps=options.get("substeps"),
                          step=step, time_unit=options["time_unit"], criterion=criterion,
                          resonance_order=resonance_order,
                          use_scene_step=check and step is None).to_dict()


def print_impulse_modes(data: dict[str, Any], check: bool) -> None:
    """The text form of :meth:`stepsafe.api.md_reports.ImpulseModesReport.to_dict`."""
    unit = data["time_unit"]
    u = f" {unit}" if unit else ""
    per = f"rad/{unit}" if unit else "rad per time unit"
    modes = data["modes"]
    size = f"{len(modes)} mode(s)" if modes else "coupled modes"
    click.echo(f"{data['method']} with {data['substeps']} substep(s) per outer drift, "
               f"{size} (criterion: {data['criterion']})")
    if not check or data["safe"] is None:
        if data["h_max"] and not modes:
            click.echo(f"Safe outer steps: 0 < H < {fmt_below(data['h_max'])}{u}")
        elif data["h_max"]:
            lim = modes[data["limiting_mode"]]
            name = lim["label"] or f"mode {data['limiting_mode']}"
            click.echo(f"Safe outer steps: 0 < H < {fmt_below(data['h_max'])}{u}, limited by "
                       f"{name} (fast {fmt(lim['fast'])}, slow {fmt(lim['slow'])} {per}; "
                       f"Omega H / pi = {lim['fast'] * data['h_max'] / 3.141592653589793:.4g})")
        else:
            click.echo("No safe outer step from 0.")
        for lo, hi in data["safe_h"][1:]:
            end = "the horizon" if hi is None else f"{fmt(hi)}{u}"
            click.echo(f"  also safe: {fmt(lo)}{u} < H < {end}")
        if data["horizon"] is not None:
            click.echo(f"Outer steps above {fmt(data['horizon'])}{u} were not analysed.")
    if not modes:
        click.echo(f"  {data['analysis']}")
    else:
        _mode_table(modes, per, unit)
    if data["step"] is not None:
        if data["safe"]:
            click.echo(f"SAFE: H = {fmt(data['step'])}{u} for every mode")
        else:
            click.echo(f"UNSAFE: H = {fmt(data['step'])}{u}")
            for failure in data["failures"]:
                name = failure["label"] or (f"mode {failure['mode']}"
                                            if failure["mode"] is not None else "the system")
                click.echo(f"  {name}: {failure['reason']}")


def _mode_table(modes: list, per: str, unit: str | None) -> None:
    click.echo(f"  {'mode':<18} {'fast':>10} {'slow':>10}  {'H max':>10}  first unsafe H "
               f"(frequencies in {per}, H in {unit or 'time units'})")
    for i, mode in enumerate(modes):
        band = mode["bands"][0] if mode["bands"] else None
        first = "-"
        if band is not None:
            end = "the horizon" if band["hi"] is None else f"{band['hi']:.6g}"
            what = {"unstable": "unstable", "resonance": "M = ±I within rounding",
                    "nonlinear": "past the resonance order asked for"}[band["kind"]]
            first = f"{band['lo']:.6g} to {end} ({what})"
        hmax = "none" if mode["h_max"] is None else f"{mode['h_max']:.6g}"
        click.echo(f"  {(mode['label'] or f'mode {i}')[:18]:<18} {mode['fast']:>10.6g} "
                   f"{mode['slow']:>10.6g}  {hmax:>10}  {first}")


def impulse_region(integrator: Any, ratio: float | None, substeps: int | None,
                   zmax: float | None, criterion: str, as_json: bool, other: bool) -> None:
    """``stepsafe region`` of an impulse method at the frequency ratio ``ratio``."""
    if integrator.kind != "impulse":
        raise _input_error(f"--ratio and --substeps apply to impulse methods; "
                           f"{integrator.name} is a {integrator.kind} method")
    if other:
        raise _input_error("--model and --verify do not apply to impulse methods (their test "
                           "model is the oscillator with a fast and a slow force)")
    if ratio is None:
        raise _input_error(f"{integrator.name} is an impulse method: give the frequency ratio "
                           "--ratio omega/Omega (slow over fast), e.g. --ratio 0.1")
    report = impulse(integrator, None, substeps=substeps, fast_beta=1.0, slow_beta=ratio,
                     criterion=criterion,
                     zmax=None if zmax is None else zmax * (1.0 + ratio * ratio) ** 0.5)
    data = dataclasses.replace(report, ratio=ratio).to_dict()
    if as_json:
        print_json(data)
    else:
        click.echo(f"Steps are Omega H, the outer step in units of 1/Omega (ratio omega/Omega "
                   f"= {ratio:g}).")
        print_respa(data)
