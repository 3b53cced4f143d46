"""The geometry of each semantic class: ``(rng, variant) -> {part: [closed trimesh components]}``.

One generator per class of :mod:`unipixie.core.annotation` (:data:`GEOMETRY`), in metres at a realistic size;
the parts are the class prior's, each one or more closed components (a crown of leaf blobs, four chair legs).
Built from the primitives of :mod:`.shapes`.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from .shapes import blob, box, cone, displace_radial, revolve, rod, rotation_about_z


def _potted_plant(rng, variant):
    H = rng.uniform(0.3, 1.0)
    hp = rng.uniform(0.2, 0.32) * H
    rt = rng.uniform(0.12, 0.2) * H
    rb = rng.uniform(0.6, 0.9) * rt
    lip = rng.uniform(1.0, 1.1)
    pot = revolve([(0, 0), (rb, 0), (rt, 0.88 * hp), (rt * lip, 0.9 * hp), (rt * lip, hp), (0, hp)])
    ts = rng.uniform(0.02, 0.04) * H
    soil = revolve([(0, hp - ts), (0.93 * rt, hp - ts), (0.93 * rt, hp + 0.4 * ts), (0, hp + 0.7 * ts)])
    z0 = hp
    leaves = []
    if variant == "succulent":
        rr = rng.uniform(0.03, 0.05) * H
        trunk = [rod([0, 0, z0 - ts], [0, 0, z0 + 0.12 * H], rr)]
        n = int(rng.integers(6, 11))
        for i in range(n):
            a = 2 * np.pi * i / n + rng.uniform(-0.2, 0.2)
            length = rng.uniform(0.18, 0.3) * H
            tilt = rng.uniform(0.5, 1.1)
            d = np.array([np.cos(a) * np.sin(tilt), np.sin(a) * np.sin(tilt), np.cos(tilt)])
            c = np.array([0, 0, z0 + 0.1 * H]) + d * length * 0.5
            m = blob([0, 0, 0], [0.5 * length, 0.16 * length, 0.1 * length], rng, 0.05, 2)
            import trimesh

            R = trimesh.geometry.align_vectors([1, 0, 0], d)
            m.apply_transform(R)
            m.apply_translation(c)
            leaves.append(m)
    else:
        top = H
        crown_r = rng.uniform(0.18, 0.3) * H if variant == "shrub" else rng.uniform(0.12, 0.2) * H
        crown_z = top - crown_r
        rr = (rng.uniform(0.025, 0.045) if variant == "shrub" else rng.uniform(0.015, 0.03)) * H
        bend = rng.normal(0, 0.04, 2) * H
        mid = np.array([bend[0], bend[1], 0.5 * (z0 + crown_z)])
        tipz = crown_z + 0.3 * crown_r
        trunk = [rod([0, 0, z0 - ts], mid, rr), rod(mid, [bend[0] * 0.5, bend[1] * 0.5, tipz], rr * 0.8)]
        n = int(rng.integers(3, 8)) if variant == "shrub" else int(rng.integers(2, 5))
        centre = np.array([bend[0] * 0.5, bend[1] * 0.5, crown_z])
        for i in range(n):
            off = rng.normal(0, 0.45, 3) * crown_r * np.array([1, 1, 0.6])
            r = crown_r * rng.uniform(0.45, 0.75)
            leaves.append(blob(centre + off, [r, r * rng.uniform(0.8, 1.2), r * rng.uniform(0.6, 0.9)], rng, 0.12, 2))
    return {"pot": [pot], "soil": [soil], "leaves": leaves, "trunk": trunk}


def _sport_ball(rng, variant):
    R = {"soccer": 0.11, "basketball": 0.12, "tennis": 0.0335, "volleyball": 0.105}[variant] * rng.uniform(0.95, 1.05)
    t = rng.uniform(0.1, 0.16) if variant == "tennis" else rng.uniform(0.06, 0.1)
    squash = rng.uniform(0.97, 1.0)
    cover = blob([0, 0, 0], [R, R, R * squash], rng, 0.0, 3)
    core = blob([0, 0, 0], [R * (1 - t), R * (1 - t), R * squash * (1 - t)], rng, 0.0, 3)
    return {"cover": [cover], "core": [core]}


def _stuffed_toy(rng, variant):
    S = rng.uniform(0.15, 0.45)
    bw = rng.uniform(0.22, 0.3) * S
    body = blob([0, 0, 0.28 * S], [bw, bw * rng.uniform(0.8, 0.95), 0.28 * S], rng, 0.03, 3)
    hr = rng.uniform(0.17, 0.22) * S
    hz = 0.56 * S + 0.8 * hr
    head = blob([0, 0, hz], [hr, hr * 0.95, hr * 0.92], rng, 0.03, 3)
    limbs = []
    lr = rng.uniform(0.06, 0.085) * S
    for s in (-1, 1):
        limbs.append(blob([s * (bw + 0.3 * lr), 0.02 * S, 0.38 * S], [lr * 1.1, lr, 0.17 * S], rng, 0.02, 2))
        limbs.append(blob([s * 0.45 * bw, -0.6 * bw, 0.07 * S], [lr * 1.1, 0.19 * S, lr * 1.0], rng, 0.02, 2))
    ears = []
    for s in (-1, 1):
        if variant == "bunny":
            ears.append(blob([s * 0.45 * hr, 0, hz + hr * 1.4], [0.28 * hr, 0.14 * hr, 0.8 * hr], rng, 0.02, 2))
        elif variant == "cat":
            ears.append(cone([s * 0.55 * hr, 0, hz + 0.6 * hr], [s * 0.3, 0, 1], 0.35 * hr, 0.6 * hr))
        else:
            ears.append(blob([s * 0.7 * hr, 0, hz + 0.75 * hr], [0.3 * hr, 0.15 * hr, 0.3 * hr], rng, 0.0, 2))
    er = rng.uniform(0.08, 0.12) * hr
    eyes = [blob([s * 0.38 * hr, -0.86 * hr, hz + 0.2 * hr], [er, er, er], rng, 0.0, 2) for s in (-1, 1)]
    eyes.append(blob([0, -0.97 * hr, hz - 0.12 * hr], [1.3 * er, er, er], rng, 0.0, 2))
    return {"body": [body], "limbs": limbs, "head": [head], "ears": ears, "eyes": eyes}


def _rubber_duck(rng, variant):
    L = rng.uniform(0.07, 0.2)
    bh = rng.uniform(0.26, 0.32) * L
    body = blob([0, 0, bh], [0.5 * L, 0.38 * L, bh], rng, 0.04, 3)
    tail = blob([0.42 * L, 0, 1.45 * bh], [0.12 * L, 0.12 * L, 0.14 * L], rng, 0.0, 2)
    hr = rng.uniform(0.2, 0.25) * L
    hc = np.array([-0.22 * L, 0, 1.75 * bh + 0.6 * hr])
    head = blob(hc, [hr, hr, hr], rng, 0.02, 3)
    beak = blob(hc + np.array([-0.95 * hr, 0, -0.15 * hr]), [0.45 * hr, 0.4 * hr, 0.15 * hr], rng, 0.0, 2)
    er = 0.12 * hr
    eyes = [blob(hc + np.array([-0.7 * hr, s * 0.45 * hr, 0.35 * hr]), [er, er, er], rng, 0.0, 1) for s in (-1, 1)]
    return {"body": [body, tail], "head": [head], "beak": [beak], "eyes": eyes}


def _jelly_pudding(rng, variant):
    h = rng.uniform(0.05, 0.12)
    rb = rng.uniform(0.45, 0.7) * h
    rt = rb * (rng.uniform(0.6, 0.85) if variant != "panna_cotta" else rng.uniform(0.85, 1.0))
    Rp = rb * rng.uniform(1.5, 2.1)
    tp = rng.uniform(0.05, 0.1) * h
    plate = revolve([(0, 0), (0.8 * Rp, 0), (Rp, tp), (0.95 * Rp, 1.2 * tp), (0, 1.0 * tp)])
    z0 = 0.95 * tp
    jelly = revolve([(0, z0), (rb, z0), (0.5 * (rb + rt) * 1.03, z0 + 0.5 * h), (rt, z0 + 0.95 * h),
                      (0.6 * rt, z0 + h), (0, z0 + h)], 48)
    if variant == "gelatin":
        jelly = displace_radial(jelly, rng, 0.05, 4)
        top = blob([0, 0, z0 + h], [0.45 * rt, 0.45 * rt, 0.3 * rt], rng, 0.1, 2)
    else:
        th = rng.uniform(0.08, 0.15) * h
        top = revolve([(0, z0 + h - th), (rt * 1.02, z0 + h - th), (rt * 1.04, z0 + h + 0.2 * th), (0, z0 + h + 0.3 * th)], 48)
    return {"plate": [plate], "jelly": [jelly], "topping": [top]}


def _metal_tool(rng, variant):
    if variant == "hammer":
        Lh = rng.uniform(0.25, 0.35)
        r = rng.uniform(0.012, 0.018)
        handle = rod([0, 0, r], [Lh, 0, r], r, 16)
        hl = rng.uniform(0.09, 0.13)
        hw = rng.uniform(0.022, 0.03)
        head = box([Lh + 0.3 * hw, 0, hw / 2], [hw * 1.6, hl, hw])
        face = rod([Lh + 0.3 * hw, -0.5 * hl, hw / 2], [Lh + 0.3 * hw, -0.62 * hl, hw / 2], 0.45 * hw, 16)
        return {"handle": [handle], "body": [head, face]}
    if variant == "can":
        R = rng.uniform(0.028, 0.042)
        H = R * rng.uniform(2.5, 4.0)
        t = rng.uniform(0.08, 0.12) * R
        body = revolve([(0, 0), (0.9 * R, 0), (R, 0.06 * H), (R, 0.94 * H), (0.9 * R, H), (0, H)], 40)
        contents = revolve([(0, t), (0.9 * R - t, t), (R - t, 0.07 * H), (R - t, 0.93 * H), (0.9 * R - t, H - t),
                             (0, H - t)], 40)
        return {"body": [body], "contents": [contents]}
    L = rng.uniform(0.15, 0.25)
    w = rng.uniform(0.13, 0.17) * L
    th = rng.uniform(0.07, 0.1) * L
    import trimesh

    shaft = box([0, 0, th / 2], [L, w, th])
    ring = trimesh.creation.annulus(r_min=0.7 * w, r_max=1.25 * w, height=th, sections=24)
    ring.apply_translation([-L / 2 - w, 0, th / 2])
    jaw = box([L / 2 + w, 0, th / 2], [2.2 * w, 2.2 * w, th])
    return {"body": [shaft, ring, jaw]}


def _sand_pile(rng, variant):
    R = rng.uniform(0.1, 0.35)
    h = rng.uniform(0.3, 0.6) * R
    zs = np.linspace(0, h, 9)
    rs = R * np.sqrt(np.clip(-np.log(np.clip(zs / h, 1e-3, 1.0)) / 5.0, 0, 1)) + 1e-4
    prof = [(0, 0)] + [(float(r), float(z)) for r, z in zip(rs, zs)][:-1] + [(0, h)]
    sand = displace_radial(revolve(prof, 48), rng, 0.06, 5)
    pebbles = []
    if variant != "fine":
        for _ in range(int(rng.integers(2, 6))):
            a = rng.uniform(0, 2 * np.pi)
            rr = rng.uniform(0.2, 0.75) * R
            z = np.interp(rr, rs[::-1], zs[::-1])
            pr = rng.uniform(0.05, 0.1) * R
            pebbles.append(blob([rr * np.cos(a), rr * np.sin(a), max(z - 0.3 * pr, pr * 0.6)],
                                 [pr, pr * rng.uniform(0.7, 1.0), pr * 0.7], rng, 0.1, 2))
    return {"sand": [sand], "pebbles": pebbles} if pebbles else {"sand": [sand]}


def _snow_pile(rng, variant):
    if variant == "snowman":
        S = rng.uniform(0.5, 1.2)
        r1, r2, r3 = S * rng.uniform(0.19, 0.23), S * rng.uniform(0.14, 0.17), S * rng.uniform(0.1, 0.12)
        z1 = 0.9 * r1
        z2 = z1 + 0.85 * (r1 + r2)
        z3 = z2 + 0.85 * (r2 + r3)
        snow = [blob([0, 0, z1], [r1, r1, 0.92 * r1], rng, 0.03, 3), blob([0, 0, z2], [r2, r2, r2], rng, 0.03, 3),
                blob([0, 0, z3], [r3, r3, r3], rng, 0.02, 3)]
        nose = [cone([0, -0.85 * r3, z3], [0, -1, -0.1], 0.18 * r3, rng.uniform(0.6, 1.0) * r3)]
        arms = []
        for s in (-1, 1):
            p0 = np.array([s * 0.6 * r2, 0, z2 + 0.2 * r2])
            p1 = p0 + np.array([s * rng.uniform(0.9, 1.3) * r2, rng.normal(0, 0.2) * r2, rng.uniform(0.3, 0.8) * r2])
            arms.append(rod(p0, p1, 0.06 * r2, 10))
        return {"snow": snow, "nose": nose, "arms": arms}
    R = rng.uniform(0.15, 0.5)
    h = rng.uniform(0.35, 0.7) * R
    snow = blob([0, 0, 0.0], [R, R * rng.uniform(0.75, 1.0), h], rng, 0.08, 3, waves=6)
    v = np.asarray(snow.vertices).copy()
    v[:, 2] = np.maximum(v[:, 2], 0.0)  # flat base: squash the lower half onto the ground
    import trimesh

    snow = trimesh.Trimesh(v, snow.faces, process=True)
    snow.update_faces(snow.nondegenerate_faces())
    snow.remove_unreferenced_vertices()
    if not snow.is_watertight:
        snow = revolve([(0, 0), (R, 0), (0.7 * R, 0.6 * h), (0, h)], 40)
    ice = []
    for _ in range(int(rng.integers(1, 4))):
        a = rng.uniform(0, 2 * np.pi)
        rr = rng.uniform(0.2, 0.6) * R
        cr = rng.uniform(0.1, 0.18) * R
        ice.append(blob([rr * np.cos(a), rr * np.sin(a), max(0.6 * h * (1 - (rr / R) ** 2), cr)], [cr, 0.8 * cr, 0.7 * cr],
                        rng, 0.2, 1))
    return {"snow": [snow], "ice": ice}


def _fruit(rng, variant):
    if variant == "orange":
        R = rng.uniform(0.035, 0.05)
        flesh = blob([0, 0, R * 0.95], [R, R, 0.95 * R], rng, 0.015, 3)
        H = 1.9 * R
    elif variant == "plum":
        R = rng.uniform(0.022, 0.03)
        flesh = blob([0, 0, R * 1.1], [R, 0.9 * R, 1.1 * R], rng, 0.01, 3)
        H = 2.2 * R
    else:
        R = rng.uniform(0.035, 0.05)
        H = R * (rng.uniform(1.7, 1.9) if variant == "apple" else rng.uniform(2.3, 2.7))
        zs = np.linspace(0, 1, 12)
        if variant == "apple":
            rs = R * np.sin(np.pi * np.clip(zs * 0.96 + 0.02, 0, 1)) ** 0.6 * (1 + 0.08 * zs)
        else:
            rs = R * (0.55 + 0.45 * np.exp(-((zs - 0.3) / 0.3) ** 2)) * np.sin(np.pi * np.clip(zs * 0.96 + 0.02, 0, 1)) ** 0.5
        prof = [(0, 0.04 * H)] + [(float(r), float(z * H)) for r, z in zip(rs[1:-1], zs[1:-1])] + [(0, H * 0.96)]
        flesh = displace_radial(revolve(prof, 40), rng, 0.02, 3)
    cz = 0.5 * flesh.bounds[1][2]
    cr = rng.uniform(0.25, 0.35) * R
    core = blob([0, 0, cz], [cr, cr, 1.4 * cr], rng, 0.0, 2)
    top = flesh.bounds[1][2]
    sl = rng.uniform(0.2, 0.35) * R
    lean = rng.normal(0, 0.25, 2) * sl
    stem = rod([0, 0, top - 0.3 * sl], [lean[0], lean[1], top + sl], rng.uniform(0.05, 0.08) * R, 10)
    out = {"flesh": [flesh], "core": [core], "stem": [stem]}
    if variant in ("apple", "pear"):
        ll = rng.uniform(0.5, 0.8) * R
        a = rng.uniform(0, 2 * np.pi)
        c = np.array([np.cos(a) * 0.5 * ll, np.sin(a) * 0.5 * ll, top + 0.6 * sl])
        leaf = blob([0, 0, 0], [0.5 * ll, 0.22 * ll, 0.06 * ll], rng, 0.0, 2)
        leaf.apply_transform(rotation_about_z(a))
        leaf.apply_translation(c)
        out["leaf"] = [leaf]
    return out


def _wooden_furniture(rng, variant):
    W = rng.uniform(0.36, 0.5)
    D = W * rng.uniform(0.85, 1.05)
    hs = rng.uniform(0.42, 0.48) if variant != "stool" else rng.uniform(0.45, 0.7)
    ts = rng.uniform(0.025, 0.045)
    lw = rng.uniform(0.03, 0.045)
    round_legs = rng.uniform() < 0.5
    legs = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            x, y = sx * (W / 2 - lw), sy * (D / 2 - lw)
            if round_legs:
                legs.append(rod([x, y, 0], [x, y, hs - ts * 0.5], lw / 2, 12))
            else:
                legs.append(box([x, y, (hs - ts * 0.5) / 2], [lw, lw, hs - ts * 0.5]))
    seat = box([0, 0, hs - ts / 2], [W, D, ts])
    out = {"legs": legs, "seat": [seat]}
    if variant != "stool":
        hb = rng.uniform(0.35, 0.5)
        posts = [box([sx * (W / 2 - lw), D / 2 - lw / 2, hs + hb / 2 - ts / 2], [lw, lw, hb]) for sx in (-1, 1)]
        rail = box([0, D / 2 - lw / 2, hs + hb - rng.uniform(0.05, 0.12)], [W, lw * 0.8, rng.uniform(0.08, 0.15)])
        out["backrest"] = posts + [rail]
    ct = rng.uniform(0.03, 0.07) if variant != "stool" else rng.uniform(0.025, 0.045)
    cushion = blob([0, 0, hs + ct / 2 - 0.002], [0.45 * W, 0.45 * D, ct / 2 + 0.002], rng, 0.02, 3)
    v = np.asarray(cushion.vertices).copy()  # flatten towards a pillow: push the sides out
    import trimesh

    rxy = np.abs(v[:, :2] - v[:, :2].mean(0)) / np.array([0.45 * W, 0.45 * D])
    v[:, :2] = v[:, :2].mean(0) + (v[:, :2] - v[:, :2].mean(0)) * (1 + 0.25 * (1 - rxy ** 2))
    cushion = trimesh.Trimesh(v, cushion.faces, process=False)
    out["cushion"] = [cushion]
    return out


GEOMETRY: dict[str, Callable] = {
    "potted_plant": _potted_plant, "sport_ball": _sport_ball, "stuffed_toy": _stuffed_toy,
    "rubber_duck": _rubber_duck, "jelly_pudding": _jelly_pudding, "metal_tool": _metal_tool,
    "sand_pile": _sand_pile, "snow_pile": _snow_pile, "fruit": _fruit, "wooden_furniture": _wooden_furniture,
}
"""Semantic class -> geometry generator ``(rng, variant) -> {part: [closed trimesh components]}``."""
