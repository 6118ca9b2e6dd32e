"""Opens files adflex wrote with their makers' (or an independent) reader and prints what it
found as one JSON object per file; exits non-zero on the first file a reader rejects.

Usage: check_files.py FILE... (.usda: Pixar's usd-core; .ply: plyfile)

For a USD stage: every prim's type and whether it is a registered schema type, whether
`points` is time-sampled, and for every boundable prim that its `extent` is authored and equals
(within float rounding) what USD computes from the prim's points and widths at each time code.
"""

import json
import sys


def check_usd(path):
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(path)
    if stage is None:
        raise SystemExit(f"{path}: usd-core could not open the stage")
    out = {"file": path, "default_prim": str(stage.GetDefaultPrim().GetPath()), "prims": []}
    times = range(int(stage.GetStartTimeCode()), int(stage.GetEndTimeCode()) + 1)
    for prim in stage.Traverse():
        info = {
            "path": str(prim.GetPath()),
            "type": str(prim.GetTypeName()),
            "schema": bool(prim.GetPrimTypeInfo().GetSchemaType()),
        }
        pts = prim.GetAttribute("points")
        if pts:
            info["points_time_samples"] = len(pts.GetTimeSamples())
        if prim.IsA(UsdGeom.Boundable):
            b = UsdGeom.Boundable(prim)
            ext = b.GetExtentAttr()
            info["extent_authored"] = bool(ext.HasAuthoredValue())
            worst = 0.0
            for t in times:
                code = Usd.TimeCode(t)
                have = ext.Get(code)
                want = UsdGeom.Boundable.ComputeExtentFromPlugins(b, code)
                if want is None and prim.IsA(UsdGeom.Points):
                    # USD's Points extent plugin takes one width per point; a constant
                    # width (one value) is that width for every point.
                    pts_prim = UsdGeom.Points(prim)
                    points = pts_prim.GetPointsAttr().Get(code)
                    widths = pts_prim.GetWidthsAttr().Get(code)
                    if points is not None and widths is not None and len(widths) == 1:
                        want = UsdGeom.Points.ComputeExtent(points, [widths[0]] * len(points))
                if have is None or want is None:
                    info["extent_missing_at"] = t
                    worst = None
                    break
                for a, c in zip(list(have), list(want)):
                    if worst is None:
                        break
                    for x, y in zip(a, c):
                        scale = max(1.0, abs(y))
                        worst = max(worst, abs(x - y) / scale)
            info["extent_error"] = worst
        out["prims"].append(info)
    return out


def check_ply(path):
    from plyfile import PlyData

    ply = PlyData.read(path)
    out = {"file": path, "elements": {}}
    for el in ply.elements:
        out["elements"][el.name] = {"count": el.count, "properties": [p.name for p in el.properties]}
    v = ply["vertex"]
    xs = [(float(a), float(b), float(c)) for a, b, c in zip(v["x"], v["y"], v["z"])]
    out["first_vertex"] = list(xs[0]) if xs else None
    return out


def main(paths):
    for p in paths:
        if p.endswith(".usda") or p.endswith(".usd"):
            print(json.dumps(check_usd(p)))
        elif p.endswith(".ply"):
            print(json.dumps(check_ply(p)))
        else:
            raise SystemExit(f"{p}: no reader for this extension")


if __name__ == "__main__":
    main(sys.argv[1:])
