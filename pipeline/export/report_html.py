"""report.html: one self-contained page (inline CSS, pictures as ``data:`` URIs, no script, no network) that
a scientist reads top to bottom: headline numbers, how the mode was chosen, held-out scores, restoration
against ground truth, the pictures, the speed-vs-error curve, the water decision, timings and the config.
"""

from __future__ import annotations

import base64
import json
import math
from html import escape
from typing import TYPE_CHECKING, Any

from pipeline.export.report_survey import survey_html
from pipeline.restore.dewater import CONFIDENCE_ERROR

if TYPE_CHECKING:
    from pipeline.export.report import Pictures

_CSS = """
body{font:14px/1.45 system-ui,sans-serif;margin:24px auto;max-width:1150px;color:#1b2730;background:#fff}
h1{font-size:22px;margin:0 0 4px}h2{font-size:17px;margin:28px 0 8px;border-bottom:1px solid #cfd8dc}
table{border-collapse:collapse;margin:6px 0}td,th{border:1px solid #cfd8dc;padding:3px 8px;text-align:right}
th{background:#eef3f5}td.l,th.l{text-align:left}.muted{color:#5f7480}
.warn{color:#8a1c12}.box{border:2px solid #c0392b;background:#fdf0ee;border-radius:6px;padding:8px 12px;margin:10px 0}
.ok{border:1px solid #cfd8dc;border-radius:6px;padding:8px 12px;margin:10px 0}
.head{display:flex;flex-wrap:wrap;gap:10px;margin:12px 0}
.kpi{border:1px solid #cfd8dc;border-radius:6px;padding:8px 12px;min-width:130px}
.kpi b{display:block;font-size:19px}
.row{display:flex;gap:8px;margin:6px 0 14px;flex-wrap:wrap}
figure{margin:0;flex:1 1 0;min-width:150px;max-width:300px}
figure img{width:100%;image-rendering:pixelated;display:block}
figure.wide{max-width:560px;min-width:240px}figure.wide img{image-rendering:auto}
figcaption{font-size:12px;color:#5f7480}pre{background:#f5f8f9;padding:10px;overflow:auto;font-size:12px}
"""


def data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def fmt(x: Any, digits: int = 2) -> str:
    if x is None:
        return "—"
    if isinstance(x, float):
        return f"{x:.{digits}f}"
    return escape(str(x))


def table(header: list[str], rows: list[list[Any]], digits: int = 2) -> str:
    head = "".join(f'<th class="{"l" if i == 0 else ""}">{escape(h)}</th>' for i, h in enumerate(header))
    body = "".join("<tr>" + "".join(f'<td class="{"l" if i == 0 else ""}">{fmt(c, digits)}</td>'
                                    for i, c in enumerate(r)) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _figures(cells: list[tuple[str, bytes]], wide: int = 0) -> str:
    """A row of captioned pictures; the first ``wide`` of them at the larger size (photo | restored)."""
    return '<div class="row">' + "".join(
        f'<figure{" class=wide" if i < wide else ""}><img src="{data_uri(png)}" alt="{escape(label)}">'
        f'<figcaption>{escape(label)}</figcaption></figure>'
        for i, (label, png) in enumerate(cells)) + "</div>"


def _restored_photos(r: dict, pics: Pictures) -> str:
    """Your photos, de-watered: what the restore stage did, its scores against ground truth, the pictures."""
    rs = r.get("restore")
    html = "<h2>Your photos, de-watered</h2>"
    if rs is None:
        return html + "<p class=muted>Not restored (the job ran before the restore stage existed).</p>"
    if rs["restored"] == 0:
        return html + f"<p><b>No photo was restored.</b> {escape(rs.get('note') or '')}</p>"
    views = rs["views"]
    size = {f"{v['width']}x{v['height']}" for v in views if "width" in v}
    surface = [v["surface"] for v in views if v.get("surface") is not None]
    capped = [v["capped"] for v in views if v.get("capped") is not None]
    extended = [v["extended"] for v in views if v.get("extended") is not None]
    html += (f"<p>{rs['restored']} photos restored at their own resolution ({escape(', '.join(sorted(size)))}) "
             f"and lens geometry into <code>restored/</code>: each pixel is the photo's own (I − B) / A, with the "
             f"water the model learned at that pixel's range from the reconstruction, where the water lets "
             f"enough light through, and leans on the model's reconstruction of that spot where it does not; no "
             f"channel is amplified more than {fmt(rs['max_gain'], 1)} times (the confidence map is the expected "
             f"error made a score: 1/2 where the error expected from the water's uncertainty, the photo's noise "
             f"and what the model lacks is {fmt(255 * CONFIDENCE_ERROR, 0)} of 255). "
             + (f"Restored surface: {fmt(100 * min(surface), 0)}–{fmt(100 * max(surface), 0)} % of each photo. "
                + (f"Seabed next to it that the model does not hold: up to {fmt(100 * max(extended), 0)} % of a "
                   f"photo, de-watered from the photo alone at the depth carried on from the surface (confidence "
                   f"0, marked in the surface mask). " if extended and max(extended) > 0 else "")
                + "The rest (open water, seabed too far to tell from it) is left as photographed and has "
                  "confidence 0. " if surface else "")
             + (f"Pixels at the gain cap: up to {fmt(100 * max(capped), 1)} %. " if capped else "")
             + f"{fmt(rs['seconds'], 1)} s in all.</p>")
    if rs.get("not_restored"):
        html += ("<p class=warn>Not restored: " + escape(", ".join(f"{x['name']} ({x['reason']})"
                                                                  for x in rs["not_restored"])) + "</p>")
    html += _exposure(r.get("exposure")) + _fall_off(r.get("fall_off"))
    html += _consistency(r.get("consistency"))
    truth = rs.get("truth")
    if truth:
        rows = [[label, truth[k]["restored_psnr"], truth[k]["render_psnr"], truth[k]["photo_psnr"],
                 truth[k]["restored_offset_px"], truth[k]["render_offset_px"]]
                for label, k in (("held-out photos", "test"), ("training photos", "train")) if truth.get(k)]
        html += ("<p class=muted>Against the true clean images at full resolution over the seabed pixels "
                 f"({escape(truth['compared'])}):</p>"
                 + table(["photos", "restored PSNR (dB)", "model render upsampled (dB)", "photo (dB)",
                          "restored edge offset (px)", "render edge offset (px)"], rows, 3))
    return html + "".join(f"<p class=muted>{escape(name)}</p>" + _figures(cells, wide=2)
                          for name, cells in pics.originals)


def _exposure(e: dict | None) -> str:
    """The training views' learned exposure and white balance (``pipeline.train.exposure``), in one sentence."""
    if not e or not e.get("views"):
        return ""
    if str(e.get("source", "")).startswith("none"):
        return ("<p><b>Exposure:</b> the photos showed no change of exposure or white balance between them (their "
                "sparse points' colours agree within the fit's noise); none was corrected.</p>")
    return (f"<p><b>Exposure:</b> the photos' exposure and white balance varied by up to "
            f"{fmt(100 * e['max_deviation'], 0)} % from the survey's mean (a gain per channel and photo, learned with "
            f"the model; per photo in the JSON report). The restored photos are at the mean exposure.</p>")


def _fall_off(f: dict | None) -> str:
    """The photos' in-frame fall-off, in one sentence (none below 5 % over the frame)."""
    if not f or f.get("span") is None or f["span"] < 1.05:
        return ""
    return (f"<p><b>Fall-off over the frame:</b> the photos are {fmt(f['span'], 2)}x brighter at the brightest place "
            f"of the frame than at the darkest (vignetting, the light's cone), whatever they show. It was measured "
            f"beside the exposure and kept out of the water's measurement; "
            + ("it was divided out of the photos for training and of the restored photos: they are as an even light "
               "would have shown them.</p>" if f.get("removed")
               else f"the restored photos keep it ({f.get('reason') or 'a job from before it was removed'}).</p>"))


def _consistency(c: dict | None) -> str:
    """The truth-free score (``pipeline.evaluate.consistency``): one plain sentence, the per-channel numbers."""
    if not c:
        return ""
    if not c.get("defined"):
        return f"<p class=muted>Colour agreement across distances: not measured ({escape(c.get('reason') or '')}).</p>"
    p, q = c["photo"], c["restored"]
    html = (f"<p><b>Colour agreement across distances (no ground truth needed):</b> between the survey's near and "
            f"far sightings ({fmt(c['range_ratio'], 2)}x the range), the colour of the same seabed point changes by "
            f"{fmt(100 * c['restored_score'], 0)} % of the colour differences between seabed points in the restored "
            f"photos (the photos: {fmt(100 * c['photo_score'], 0)} %): "
            + (f"the restoration removed {fmt(100 * (1 - c['share']), 0)} % of the photos' change with distance"
               if c["share"] < 1 else f"<span class=warn>the restoration added {fmt(100 * (c['share'] - 1), 0)} % "
                                      f"to the photos' change with distance</span>")
            + f"; from {c['n_points']} sparse points seen at clearly different ranges ({c['n_sightings']} "
              f"sightings).</p>")
    rows = [[name, 100 * p["score"][k], 100 * q["score"][k], q["contrast"][k] / p["contrast"][k]]
            for k, name in enumerate(("red", "green", "blue"))]
    return html + table(["channel", "photos: change with distance (%)", "restored (%)",
                         "restored / photo contrast"], rows, 1)


def no_water_removed(r: dict) -> bool:
    """Mode ``3dgs`` models no water: nothing was removed, whatever ``restored/`` holds (the model itself)."""
    return r["mode"] == "3dgs"


def _kpis(r: dict) -> str:
    t, rest = r["metrics"]["test"], r["restoration"]
    w = r["water"]
    water = w["water_type"] if w else None
    if water == "unknown":
        water = f"unknown (closest {w.get('closest')})"
    items = [("mode", r["mode"]), ("preset", r["preset"]), ("water", water),
             (f"held-out PSNR ({t['n_views']} views)", f"{fmt(t['psnr'])} dB"), ("held-out SSIM", fmt(t["ssim"], 3)),
             ("LPIPS", fmt(t["lpips"], 3))]
    if rest is not None and not no_water_removed(r):
        items.append(("restored J PSNR vs truth", f"{fmt(rest['restored']['psnr'])} dB"))
    c = r.get("consistency") or {}
    if c.get("defined"):  # the truth-free restoration score (section "Your photos, de-watered")
        items.append(("colour change with distance", f"{fmt(100 * c['restored_score'], 0)} % "
                                                     f"(photos {fmt(100 * c['photo_score'], 0)} %)"))
    items += [("Gaussians", r["model"]["n_gaussians"]), ("total time", f"{fmt(r['timings']['total_s'], 0)} s")]
    return '<div class="head">' + "".join(f'<div class="kpi"><span class="muted">{escape(k)}</span>'
                                          f"<b>{fmt(v) if not isinstance(v, str) else escape(v)}</b></div>"
                                          for k, v in items) + "</div>"


def _inputs(r: dict) -> str:
    """The input's name and image count, and the SfM summary (registered / total, reprojection error, matcher)."""
    inp, sfm = r.get("input") or {}, r.get("sfm")
    skipped = f", {inp['skipped']} undecodable file(s) skipped" if inp.get("skipped") else ""
    html = (f"<h2>Input and camera poses</h2><p>Input <b>{fmt(inp.get('name'))}</b>: {fmt(inp.get('images'))} "
            f"images{skipped}.</p>")
    if not sfm:
        return html + "<p class=muted>No SfM summary (the sfm stage has not run).</p>"
    return html + (f"<p>SfM registered <b>{fmt(sfm['registered'])} of {fmt(sfm['total'])}</b> images, mean "
                   f"reprojection error {fmt(sfm['mean_reproj_error_px'], 3)} px, {fmt(sfm['num_points3D'])} "
                   f"points, {fmt(sfm['matcher'])} matching.</p>" + _split(sfm) + _dropped(sfm))


def _split(sfm: dict) -> str:
    """The images left out when the survey broke into several models (only the largest was used)."""
    others = sfm.get("other_models") or []
    if not others:
        return ""
    parts = "; ".join(f"{m['registered']} images ({escape(', '.join(m['images']))})" for m in others)
    return (f"<p><b>The survey broke into {len(others) + 1} models</b>; only the largest was used. Left out: "
            f"{parts}.</p>")


def _dropped(sfm: dict) -> str:
    """Each frame the kept model does not place, with SfM's reason (``SfmSummary.dropped``)."""
    dropped = sfm.get("dropped") or []
    if not dropped:
        return ""
    items = "".join(f"<li>{escape(d['name'])}: {escape(d['reason'])}</li>" for d in dropped)
    return f"<p>{len(dropped)} frame(s) left out of the model:</p><ul>{items}</ul>"


def _schedule(s: dict | None) -> str:
    """How the run's length and budget followed the survey (``pipeline.train.schedule``)."""
    if not s:
        return ""
    length = ("set by --iterations (the rule would scale the preset by "
              f"{fmt(s['factor'])})" if s["explicit_iterations"] else f"the preset x {fmt(s['factor'])}")
    cap = fmt(s["max_gaussians"]) if s["max_gaussians"] else "none"
    medium = f"; the water model starts after iteration {fmt(s['medium_start'])}" if s["medium_start"] else ""
    coarse = (f". Iterations 1-{fmt(s['coarse_until'])} trained at {fmt(s['coarse_width'])}x"
              f"{fmt(s['coarse_height'])} (the coarse start)" if s.get("coarse_until") else "")
    return (f"<h2>Schedule</h2><p>{fmt(s['views'])} views ({fmt(s['train_views'])} trained on) at "
            f"{fmt(s['width'])}x{fmt(s['height'])}: {fmt(s['pixels'])} training pixels. Rule: "
            f"<code>{escape(s['rule'])}</code>. <b>{fmt(s['iterations'])} iterations</b>, {length}: "
            f"{fmt(s['passes'], 1)} passes over the training views. Densification every {fmt(s['refine_every'])} "
            f"iterations from {fmt(s['refine_start'])} to {fmt(s['refine_stop'])}, opacity reset every "
            f"{fmt(s['reset_every'])}; Gaussian budget {cap}{medium}{coarse}.</p>")


def _selection(r: dict) -> str:
    """The mode decision with the water-type decision beside it, and what the mode means for restoration."""
    sel, w = r["selection"], r["water"]
    water = f"Water classified {water_sentence(w)}." if w else "Water type not classified."
    html = f"<h2>Model selection</h2><p>Mode <b>{escape(sel['mode'])}</b>: {escape(sel['reason'])}. {water}</p>"
    d = sel.get("drift") or {}
    if d.get("score") is not None:
        html += (f"<p>In the photos, the same seabed point's colour changes between near and far sightings by "
                 f"{fmt(d['score'], 3)} of the seabed's contrast (largest channel; water makes it 0.29 or more, "
                 f"photos without water stay below 0.12)"
                 + ("" if d.get("defined") else f"; not used: {escape(d.get('reason') or '')}") + ".</p>")
    if no_water_removed(r):
        html += ("<p><b>No water was removed.</b> Mode 3dgs fits the photos as they are, with no model of the "
                 "water, so there is no restored image J; the views below show the model with the water in them"
                 + (f" (the mode was chosen because: {escape(sel['reason'])})" if sel.get("reason") else "")
                 + ".</p>")
    return html


def _restoration(rest: dict | None, r: dict | None = None) -> str:
    if rest is not None and r is not None and no_water_removed(r):
        rows = [[label, rest[k]["psnr"], rest[k]["ssim"], rest[k]["lpips"]] for label, k in (
            ("photo vs true clean J", "input"), ("model with water vs photo (alignment check)", "with_water"))]
        return ("<h2>Restoration against ground truth</h2><p>No water was removed (mode 3dgs), so there is no "
                "restored J to score; the photos themselves against the true clean images:</p>"
                + table(["comparison", "PSNR (dB)", "SSIM", "LPIPS"], rows, 3))
    if rest is None:
        return "<h2>Restoration</h2><p class=muted>No ground truth for this job (only generated scenes have it).</p>"
    rows = [[label, rest[k]["psnr"], rest[k]["ssim"], rest[k]["lpips"]] for label, k in (
        ("restored J vs true clean J", "restored"), ("photo vs true clean J (no restoration)", "input"),
        ("model with water vs photo (alignment check)", "with_water"))]
    html = ("<h2>Restoration against ground truth</h2>"
            f"<p class=muted>{escape(rest['rendered_from'])}; {len(rest['views'])} held-out views; ground truth "
            f"{escape(rest['ground_truth'])} (water preset {fmt(rest.get('water_preset'))}); one scene unit = "
            f"{fmt(rest['metres_per_unit'], 4)} m by aligning the cameras to the true ones (rotation error "
            f"{fmt(rest['alignment']['rot_err_deg_mean'], 3)}°).</p>"
            + table(["comparison", "PSNR (dB)", "SSIM", "LPIPS"], rows, 3))
    if rest.get("per_view"):
        html += table(["held-out view", "restored J PSNR (dB)", "photo PSNR (dB)", "gain (dB)"],
                      [[p["name"], p["restored_psnr"], p["input_psnr"],
                        None if p["restored_psnr"] is None or p["input_psnr"] is None
                        else p["restored_psnr"] - p["input_psnr"]] for p in rest["per_view"]])
    seen = rest.get("seen")
    if seen is not None:
        html += (f"<p>Over the pixels some training view saw ({fmt(100 * seen['fraction'], 0)} % of them; "
                 f"{escape(seen['rule'])}): restored J {fmt(seen['restored_psnr'])} dB, the photo "
                 f"{fmt(seen['input_psnr'])} dB. Seabed no training view saw can only be invented, not "
                 f"restored.</p>")
    coef = rest["coefficients"]
    if coef is not None:
        crow = []
        for k in ("beta_D", "beta_B", "B_inf"):
            c = coef[k]
            crow += [[f"{k} {ch} ({coef['units'][k]})", c["estimated"][i], c["true"][i], c["rel_error"][i]]
                     for i, ch in enumerate("RGB")]
        html += table(["coefficient", "recovered", "true", "relative error"], crow, 3)
    else:
        html += "<p class=muted>No medium in this mode: no water coefficients recovered.</p>"
    d = rest["depth"]
    if d.get("scale_aligned") is None:
        return html + f"<p class=warn>Depth error: {escape(d.get('reason') or 'not measured')}.</p>"
    html += table(["depth error (held-out views)", "mean abs", "mean relative", "pixels"], [
        [f"least-squares scale ({fmt(d['scale_aligned']['scale'], 4)} m/unit)", d["scale_aligned"]["abs_error"],
         d["scale_aligned"]["rel_error"], d["scale_aligned"]["n_pixels"]],
        ["at the camera alignment's scale", d["at_alignment_scale"]["abs_error_m"],
         d["at_alignment_scale"]["rel_error"], d["at_alignment_scale"]["n_pixels"]]], 3)
    return html


def _curve_vs_header(r: dict) -> str:
    """Say how the curve's last point relates to the header's held-out PSNR: the same number, or two scores
    of two view sets / renders, each named."""
    pts, t = r["speed_vs_error"]["points"], r["metrics"]["test"]
    if not pts or t["psnr"] is None:
        return ""
    last = pts[-1]
    same_views = sorted(r["speed_vs_error"]["views"]) == sorted(t["views"])
    if same_views and abs(last["psnr"] - t["psnr"]) < 0.005:
        return f" Its last point ({fmt(last['psnr'])} dB) is the header's held-out PSNR."
    return (f" Its last point (iteration {last['iteration']}: {fmt(last['psnr'])} dB, training's check on "
            f"{len(r['speed_vs_error']['views'])} views: {escape(', '.join(r['speed_vs_error']['views']))}) is "
            f"not the header's held-out PSNR ({fmt(t['psnr'])} dB, the evaluate stage on {t['n_views']} views: "
            f"{escape(', '.join(t['views']))}).")


def _water(w: dict | None) -> str:
    if not w:
        return "<h2>Water type</h2><p class=muted>Not classified.</p>"
    probs = ", ".join(f"{escape(k)} {v:.2f}" for k, v in w.get("probabilities", {}).items())
    rest = [[k, json.dumps(v)] for k, v in w.items() if k not in ("water_type", "probabilities", "reason")]
    return (f"<h2>Water type</h2><p>Classified {water_sentence(w)} (probabilities {probs}).</p>"
            + table(["decision field", "value"], rest))


def water_sentence(w: dict) -> str:
    """"<b>clear</b> (p = 0.93)", or for water the classifier does not know "<b>unknown</b> (closest: clear,
    p 0.998, but ...reason; trained with the medium water's settings)". HTML, escaped."""
    probs = w.get("probabilities") or {}
    if w.get("water_type") == "unknown":
        closest = w.get("closest") or (max(probs, key=probs.get) if probs else "?")
        p = f", p {probs[closest]:.3f}" if closest in probs else ""
        why = f", but {w['reason']}" if w.get("reason") else ""
        then = f"; trained with the {w['settings_from']} water's settings" if w.get("settings_from") else ""
        return f"<b>unknown</b> (closest: {escape(closest)}{p}{escape(why)}{escape(then)})"
    p = probs.get(w["water_type"])
    conf = w.get("confidence")
    extra = (f", confidence {conf:.2f}" if conf is not None and p is not None and conf < p - 0.005 else "")
    note = f"; {w['reason']}" if w.get("reason") else ""
    return (f"<b>{escape(w['water_type'])}</b>" + (f" (p = {p:.2f}{extra}{escape(note)})" if p is not None else ""))


def _timings(t: dict) -> str:
    rows = [[f"stage {k}", v] for k, v in t["stages_s"].items()] + [["total", t["total_s"]]]
    r = t["render_ms_per_view"]
    rows += [["training iterations / s", t["train_iterations_per_s"]],
             ["training seconds (steps only)", t.get("train_elapsed_s")],
             [f"render ms per view ({r.get('width')}x{r.get('height')}, median of {r['n']})", r["median"]]]
    return "<h2>Timings</h2>" + table(["what", "seconds / rate"], rows, 2)


def _coefficients(w: dict | None) -> str:
    """The water coefficients the model learned, the sparse-point measurement and its uncertainty."""
    if not w:
        return ""
    rows = []
    for k in ("beta_D", "beta_B", "B_inf"):
        c = w[k]
        for i, ch in enumerate("RGB"):
            sig = (c.get("sigma") or [None] * 3)[i]
            if sig is None:
                spread = "not determined" if c.get("measured") else None
            elif c.get("sigma_scale") == "log":
                spread = f"×/÷ {min(math.exp(sig), 999.0):.2f}"
            else:
                spread = f"± {sig:.2f} (logit)"
            rows.append([f"{k} {ch} ({c['units']})", c["learned"][i], (c.get("measured") or [None] * 3)[i],
                         spread, (c.get("source") or [None] * 3)[i]])
    prior = w.get("prior")
    note = ("" if not prior else f" Prior where the points cannot pin a coefficient: the classified water type's "
            f"optical depth {', '.join(f'{x:g}' for x in prior['optical_depth'])} (R, G, B) at the sightings' "
            f"median range {prior['median_range']:.3g}, a factor of {math.exp(prior['sigma_log'] or 0):.1f} "
            "either way.")
    failed = [f"{ch}: {why}" for ch, why in zip("RGB", w.get("failed") or [], strict=False) if why]
    warn = ("" if not failed else "<p class=warn><b>The sparse points could not measure the water</b> in "
            + escape("; ".join(failed)) + ". The classified water type's values were used there.</p>")
    return ("<h2>Water coefficients</h2><p class=muted>Learned by the medium; measured from the sparse points "
            "before training (what the training held the medium to), with that measurement's uncertainty (one σ) "
            "and what determined it." + escape(note) + "</p>" + warn
            + table(["coefficient", "learned", "measured", "uncertainty", "source"], rows, 3))


def _quality(q: dict | None) -> str:
    """The model-quality block at the top: did the Gaussians keep the scene in every training view."""
    if not q:
        return "<div class=ok><b>Model quality</b>: not measured (job trained before the check existed).</div>"
    pc = q.get("point_coverage_min")
    cap = q.get("cap") or 0
    budget = f"budget {q['budget']:,}" + (f"; the run's cap {cap:,}" if cap > q["budget"] else "")
    line = (f"{q['n_gaussians']:,} Gaussians ({budget}); training views covered (alpha ≥ 0.5): "
            f"at least {100 * q['coverage_min']:.1f}% of pixels"
            + (f", {100 * pc:.1f}% of their sparse points" if pc is not None else "")
            + (f" ({100 * q['point_depth_min']:.0f}% or more of them at the points' distance)"
               if q.get("point_depth_min") is not None else "")
            + (f"; water share of the predicted light {100 * q['water_share_mean']:.0f}%"
               if q.get("water_share_mean") is not None else ""))
    warn = "".join(f"<li>{escape(w)}</li>" for w in q.get("warnings", []))
    cls = "box" if warn else "ok"
    rows = [[p["name"], p["coverage"], p["point_coverage"], p.get("point_depth"), p.get("uncovered_detail"),
             p["water_share"]] for p in q.get("per_view", [])]
    return (f"<div class={cls}><b>Model quality</b>: {escape(line)}."
            + (f"<ul class=warn>{warn}</ul>" if warn else " No warnings.") + "</div>"
            + "<details><summary>coverage per training view</summary>"
            + table(["view", "pixels covered", "sparse points covered", "points at their distance",
                     "uncovered with detail", "water share"], rows, 3) + "</details>")


def render_html(r: dict, pics: Pictures) -> str:
    """The page for report ``r`` with ``pics`` embedded."""
    t = r["metrics"]["test"]
    parts = [f"<h1>dualphys report: {escape(r['job']['name'])}</h1>",
             f"<p class=muted>created {escape(r['created_at'])}; report schema {r['schema_version']}</p>",
             _quality(r.get("quality")),
             _kpis(r), _inputs(r), _selection(r), _schedule(r.get("schedule")), _restored_photos(r, pics),
             "<h2>Held-out views</h2>"
             f"<p class=muted>{t['n_views']} views (every 8th by name), {escape(t['compared'])}; PSNR of the pooled "
             f"MSE, SSIM with an 11x11 Gaussian window. LPIPS: {escape(t['lpips_reason'] or 'LPIPS-VGG')}.</p>",
             table(["view", "PSNR (dB)", "SSIM", "render ms"],
                   [[p["name"], p["psnr"], p["ssim"], p["render_ms"]] for p in t["per_view"]], 3),
             _restoration(r["restoration"], r), survey_html(r.get("survey"), pics.survey, data_uri),
             "<h2>Held-out views: photo, model" + ("" if no_water_removed(r) else ", model restored")
             + (", ground truth" if r["restoration"] else "") + "</h2>"]
    parts += [f"<p class=muted>{escape(name)}</p>" + _figures(cells) for name, cells in pics.views]
    parts.append("<h2>Water maps: attenuation, backscatter, depth</h2>")
    parts += [f"<p class=muted>{escape(name)}</p>" + _figures(cells) for name, cells in pics.maps] or [
        "<p class=muted>No maps.</p>"]
    sve = r["speed_vs_error"]
    parts.append("<h2>Speed against error</h2>")
    if pics.curve is not None:
        parts.append(f'<img src="{data_uri(pics.curve)}" alt="speed against error" style="max-width:640px">')
    parts.append(f"<p class=muted>{escape(sve['metric'])} on {len(sve['views'])} held-out views against "
                 f"{escape(sve.get('time', 'training seconds'))}.{_curve_vs_header(r)}</p>"
                 + table(["iteration", "seconds", "PSNR (dB)"],
                         [[p["iteration"], p["elapsed_s"], p["psnr"]] for p in sve["points"]]))
    parts += [_water(r["water"]), _coefficients(r["model"].get("water_coefficients")), _timings(r["timings"]),
              "<h2>Config</h2><pre>" + escape(json.dumps({"job options": r["job"]["options"],
                                                          "training": r["config"]}, indent=2)) + "</pre>"]
    return ("<!DOCTYPE html><html lang=en><head><meta charset=utf-8><title>dualphys report "
            f"{escape(r['job']['name'])}</title><style>{_CSS}</style></head><body>" + "\n".join(parts)
            + "</body></html>\n")


__all__ = ["data_uri", "render_html"]
