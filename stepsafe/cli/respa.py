"""The ``respa`` command: safe outer steps of an impulse (r-RESPA) integrator."""

from __future__ import annotations

from typing import Any

import click

from stepsafe.cli.main import (
    EXIT_UNSAFE,
    FLOAT,
    INT,
    TIME_UNIT_NAMES,
    _input_error,
    _option_value,
    criterion_option,
    main,
)


def _frequency(beta, wavenumber, which: str, unit) -> float:
    from stepsafe.units import quantity

    given = [v for v in (beta, wavenumber) if v is not None]
    if len(given) != 1:
        raise _input_error(f"give the {which} frequency once: --{which}-beta B or "
                           f"--{which}-wavenumber K")
    if beta is not None:
        return beta
    return _option_value(lambda v: quantity(v, "wavenumber", unit), f"{which}-wavenumber",
                         wavenumber)


@main.command("respa")
@click.option("--outer", default="verlet", show_default=True, metavar="METHOD",
              help="Splitting over the slow force (its kicks) at the outer step H.")
@click.option("--inner", default="verlet", show_default=True, metavar="METHOD",
              help="Splitting over the fast force, run SUBSTEPS times per outer drift.")
@click.option("--substeps", type=INT, default=4, show_default=True, metavar="K",
              help="Inner steps per outer drift (inner step H/K).")
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
@click.option("--step", "step", type=FLOAT, default=None, metavar="H",
              help="Check this outer step: exit 0 if safe, 1 if not.")
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
def respa_cmd(outer, inner, substeps, fast_beta, slow_beta, fast_wavenumber, slow_wavenumber,
              time_unit, step, zmax, resonance_order, plot_file, as_json, criterion) -> None:
    """Safe outer steps of an impulse / r-RESPA multiple-time-step integrator.

    The test model is one coordinate with a fast force (frequency Omega alone) and a slow
    one (omega): the outer splitting kicks with the slow force at step H, each of its
    drifts is SUBSTEPS inner steps over the fast force. Impulse methods go unstable in
    bands near Omega H = j pi (half periods of the fast vibration), long before the inner
    method's own limit; the bands are listed with Omega H / pi. At a fixed ratio the outer
    step is exactly a splitting on the oscillator of frequency sqrt(Omega^2 + omega^2), so
    the analysis is that of `stepsafe advise`. The default criterion here is stability
    (|tr M| <= 2, the bands of the impulse literature); structure also requires the
    sense of rotation, which the outer step reverses beyond Omega H = pi.

    \b
    Examples:
      stepsafe respa --fast-beta 10 --slow-beta 1 --substeps 4
      stepsafe respa --fast-wavenumber 3700 --slow-wavenumber 300 --time-unit fs \\
          --substeps 4 --step 2
    """
    from stepsafe.cli.report import print_json
    from stepsafe.respa_advice import impulse

    fast = _frequency(fast_beta, fast_wavenumber, "fast", time_unit)
    slow = _frequency(slow_beta, slow_wavenumber, "slow", time_unit)
    report = impulse(outer, inner, substeps, fast=fast, slow=slow, step=step,
                     criterion=criterion, zmax=zmax, time_unit=time_unit,
                     resonance_order=resonance_order)
    data = report.to_dict()
    if plot_file is not None:
        _chart(outer, inner, substeps, fast, slow, plot_file)
    if as_json:
        print_json(data)
    else:
        print_respa(data)
    if step is not None and not data["safe"]:
        raise SystemExit(EXIT_UNSAFE)


def print_respa(data: dict[str, Any]) -> None:
    from stepsafe.cli.report import fmt, fmt_below

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


def _chart(outer: str, inner: str, substeps: int, fast: float, slow: float,
           output: str) -> None:
    """The plane (Omega H, omega H): shaded where one outer step is unstable (|tr M| > 2),
    up to 1.05 times the inner method's own limit in Omega H, with the ray of the ratio."""
    import numpy as np

    from stepsafe import api
    from stepsafe.cli.accuracy import _plot_format, _pyplot, _save
    from stepsafe.core.impulse import stability_chart

    plt = _pyplot()
    fmt = _plot_format(output, plt)
    outer_t, inner_t = api.method(outer).tableau, api.method(inner).tableau
    z_inner = api.region(api.method(inner), "oscillator").regions["oscillator"].first_boundary
    x_top = 1.05 * substeps * (z_inner or 10.0)
    y_top = 0.5 * x_top
    x = np.linspace(x_top / CHART_PIXELS, x_top, CHART_PIXELS)
    y = np.linspace(y_top / CHART_PIXELS, y_top, CHART_PIXELS)
    unstable = stability_chart(outer_t, inner_t, substeps, x, y) >= 1.0
    fig, ax = plt.subplots(figsize=(7, 4.5))
    ax.imshow(unstable, origin="lower", extent=(0, x_top, 0, y_top), aspect="auto",
              cmap="Greys", vmin=0, vmax=1.6, interpolation="nearest")
    ray = np.array([0.0, x_top])
    ax.plot(ray, ray * slow / fast, color="tab:red", lw=1.2, label="your ratio omega/Omega")
    from stepsafe.core.regions import find_region
    from stepsafe.core.resonances import rotations

    # the inner method's half turns: K theta_in(Omega H / K) = j pi
    inner_region = find_region(inner_t, "oscillator", x_top / substeps)
    pairs = [(2 * substeps, j) for j in range(1, substeps)]
    for r in rotations(inner_t, inner_region, pairs):
        ax.axvline(substeps * r.z, color="tab:blue", lw=0.6, ls=":")
    ax.set_xlim(0, x_top)
    ax.set_ylim(0, y_top)
    ax.set_xlabel("Omega H (fast)  [dotted: K inner steps turn by j pi]")
    ax.set_ylabel("omega H (slow)")
    ax.set_title(f"{outer}/{inner} x{substeps}: unstable where shaded")
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    _save(fig, output, fmt)
