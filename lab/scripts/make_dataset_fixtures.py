#!/usr/bin/env python3
"""Writes the tiny dataset fixtures that `lab/tests/datasets.rs` reads (no Python at test time).

    python lab/scripts/make_dataset_fixtures.py            # (re)write lab/tests/fixtures/{npz,syncar,nemo_*}
    python lab/scripts/make_dataset_fixtures.py --check-rust
        # np.load the files the Rust tests wrote (fixtures/npz/rust_written.npz) and compare them
        # with the arrays this script defines: proves Python reads what udapose writes.

Everything is written the way the real producers write it:
- `npz/`: every dtype the Rust reader supports, via np.savez / np.savez_compressed / np.save, plus
  .npy files in format versions 2.0 and 3.0 and a Fortran-order one (rejected by the reader).
- `syncar/`: SynCar-OOD (BENCHMARK.md §4): keys in the documented order, crop-frame values.
- `nemo_pascal3d/`: NeMo's original exporter (Angtian/NeMo CreatePascal3DNeMo.py): lists with `.JPEG`
  names per subtype and per mesh, original-image annotation, `occ_mask=None` (a pickled object
  array), MATLAB doubles for height/width/cad_index; `carFGL1_BGL1` holds an occluded sample.
- `nemo_oodcv/`: OOD-CV-Pose's exporter (prepare_ood_cv.py): `<split>/{images,annotations,lists}`,
  names `<image>_<obj>` without extension, `resize_rate`, `padding_params`, `nuisance`.
- `nemo_nmm/`: the neural-mesh-model exporter (wufeim/NeMo): `distance` already 5 and `px, py`
  already in the crop.
Geometry is scaled down (crops of 16×42 instead of 256×672) to keep the files tiny; the crop is
computed with NeMo's own procedure (resize by distance/5, box centred on the scaled principal point,
zero padding), so `box`, `box_obj` and the images are consistent with the annotation.
"""

import argparse
import shutil
from pathlib import Path

import numpy as np
from PIL import Image

FIXTURES = Path(__file__).resolve().parent.parent / "tests" / "fixtures"
CROP = (16, 42)  # NeMo's car crop (256, 672) / 16


def all_dtypes():
    """One array per supported dtype; the Rust test checks each value literally."""
    return {
        "f64_scalar": np.array(1.25),
        "f64_2x3": np.arange(6, dtype="<f8").reshape(2, 3) / 4 - 0.5,
        "f32_vec": np.array([1.5, -2.25, 0.125, np.inf], dtype="<f4"),
        "i64_2x2": np.array([[-1, 2**40], [3, -4]], dtype="<i8"),
        "i32_vec": np.array([-7, 0, 2**31 - 1], dtype="<i4"),
        "i16_vec": np.array([-300, 300], dtype="<i2"),
        "i8_vec": np.array([-128, 127], dtype="|i1"),
        "u64_vec": np.array([0, 2**64 - 1], dtype="<u8"),
        "u32_vec": np.array([2**32 - 1], dtype="<u4"),
        "u16_vec": np.array([65535, 1], dtype="<u2"),
        "u8_2x3": np.array([[0, 1, 255], [7, 8, 9]], dtype="|u1"),
        "bool_vec": np.array([True, False, True, True, False]),
        "bool_scalar": np.array(True),
        "str_scalar": np.array("n02814533_1234"),
        "str_vec": np.array(["café", "ü🚗", "a"]),
        "empty_f64": np.zeros((0,), dtype="<f8"),
        "f64_3d": np.arange(6.0).reshape(2, 1, 3),
        "be_f64": np.array([1.0, -2.0], dtype=">f8"),
        "none_object": np.array(None, dtype=object),
    }


def write_npz_fixtures():
    out = FIXTURES / "npz"
    out.mkdir(parents=True, exist_ok=True)
    arrays = all_dtypes()
    np.savez(out / "dtypes.npz", **arrays)
    np.savez_compressed(out / "dtypes_compressed.npz", **arrays)
    matrix = np.arange(6, dtype="<i4").reshape(2, 3)
    with open(out / "v2.npy", "wb") as f:
        np.lib.format.write_array(f, matrix, version=(2, 0))
    with open(out / "v3.npy", "wb") as f:
        np.lib.format.write_array(f, matrix, version=(3, 0))
    np.save(out / "fortran.npy", np.asfortranarray(matrix.astype("<f8")))


def write_png(path, height, width, rng):
    pixels = rng.integers(0, 256, size=(height, width, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(path, optimize=True)


def write_syncar_fixtures(rng):
    """Two source/test samples and one occ-l1/test sample (with occ_fraction)."""
    h, w = 8, 20
    samples = {
        ("source", "test"): [
            dict(azimuth=0.5, elevation=0.25, theta=-0.125, distance=6.5, fill=0.875, car="p406", cad_index=11),
            dict(azimuth=3.0, elevation=-0.1, theta=0.05, distance=9.75, fill=0.8125, car="155-DTM", cad_index=1),
        ],
        ("occ-l1", "test"): [
            dict(azimuth=1.5, elevation=0.5, theta=0.0, distance=4.25, fill=0.9, car="car1-ow1", cad_index=15,
                 occ_fraction=0.3125),
        ],
    }
    for (domain, split), annos in samples.items():
        base = FIXTURES / "syncar" / domain / split
        for sub in ("images", "annotations", "lists"):
            (base / sub / "car").mkdir(parents=True, exist_ok=True)
        names = []
        for i, a in enumerate(annos):
            name = f"{i:06d}"
            names.append(name + ".png")
            write_png(base / "images" / "car" / (name + ".png"), h, w, rng)
            mask = np.zeros((h, w), dtype=np.uint8)
            mask[2:6, 3 + i : 15 + i] = 1
            # Key order and dtypes exactly as BENCHMARK.md §4 (and the Rust writer) define them.
            keys = dict(
                azimuth=np.float64(a["azimuth"]),
                elevation=np.float64(a["elevation"]),
                theta=np.float64(a["theta"]),
                distance=np.float64(a["distance"]),
                principal=np.array([w / 2, h / 2]),
                viewport=np.float64(3000.0 * h / 256),
                focal=np.float64(1.0),
                height=np.int64(h),
                width=np.int64(w),
                fill=np.float64(a["fill"]),
                car=np.array(a["car"]),
                cad_index=np.int64(a["cad_index"]),
                mask=mask,
            )
            if "occ_fraction" in a:
                keys["occ_fraction"] = np.float64(a["occ_fraction"])
            np.savez(base / "annotations" / "car" / (name + ".npz"), **keys)
        (base / "lists" / "car" / "list.txt").write_text("".join(n + "\n" for n in names))


def nemo_crop(original, principal, distance, bbox, out_shape):
    """NeMo's crop: resize by distance/5, cut out_shape centred on the scaled principal point.

    Returns the crop and the BboxTools arrays `box`, `box_ori`, `box_obj` ([y0, y1, x0, x1, H, W],
    float32) as NeMo stores them, plus the padding."""
    h0, w0 = original.shape[:2]
    rate = distance / 5.0
    img = np.array(Image.fromarray(original).resize((int(w0 * rate), int(h0 * rate))))
    cy, cx = (np.array(principal)[::-1] * rate).astype(int)
    oh, ow = out_shape
    pad = ((max(oh // 2 - cy, 0), max(oh // 2 + cy - img.shape[0], 0)),
           (max(ow // 2 - cx, 0), max(ow // 2 + cx - img.shape[1], 0)))
    img = np.pad(img, pad + ((0, 0),), mode="constant")
    y0, x0 = cy - oh // 2 + pad[0][0], cx - ow // 2 + pad[1][0]
    crop = img[y0 : y0 + oh, x0 : x0 + ow]
    bx0, by0, bx1, by1 = (int(v) for v in bbox)
    box = np.array([y0, y0 + oh, x0, x0 + ow, img.shape[0], img.shape[1]], dtype=np.float32)
    box_ori = np.array([max(by0, 0), min(by1, h0), max(bx0, 0), min(bx1, w0), h0, w0], dtype=np.float32)
    oy0, oy1 = int(by0 * rate) + pad[0][0] - y0, int(by1 * rate) + pad[0][0] - y0
    ox0, ox1 = int(bx0 * rate) + pad[1][0] - x0, int(bx1 * rate) + pad[1][0] - x0
    box_obj = np.array([max(oy0, 0), min(oy1, oh), max(ox0, 0), min(ox1, ow), oh, ow], dtype=np.float32)
    return crop, box, box_ori, box_obj, pad, rate


def nemo_dirs(base, cat):
    for sub in ("images", "annotations", "lists"):
        (base / sub / cat).mkdir(parents=True, exist_ok=True)
    return base / "images" / cat, base / "annotations" / cat, base / "lists" / cat


def original_image(rng, h0=48, w0=64):
    return rng.integers(0, 256, size=(h0, w0, 3), dtype=np.uint8)


def save_jpeg(path, crop):
    Image.fromarray(crop).save(path, quality=40)


NEMO_SAMPLES = [
    # name, azimuth°, elevation°, theta°, distance, principal (px, py), bbox (x0, y0, x1, y1), cad
    ("n02814533_101", 30.0, 10.0, -2.0, 5.6, (31.5, 23.25), (10, 15, 50, 34), 3),
    ("n02814533_202", 200.0, 5.0, 4.0, 4.0, (3.5, 40.75), (0, 30, 10, 48), 1),
    ("n02814533_303", 350.0, 20.0, 0.0, 7.5, (40.25, 20.5), (20, 10, 60, 30), 3),
]


def mesh_params(s, h0=48, w0=64, int_dims=False):
    _, az, el, th, d, p, bbox, cad = s
    return dict(
        azimuth=np.float64(np.deg2rad(az)),
        elevation=np.float64(np.deg2rad(el)),
        theta=np.float64(np.deg2rad(th)),
        distance=np.float64(d),
        focal=np.float64(1.0),
        principal=np.array(p, dtype=np.float64),
        viewport=np.float64(3000.0),
        height=h0 if int_dims else np.float64(h0),
        width=w0 if int_dims else np.float64(w0),
        cad_index=cad if int_dims else np.float64(cad),
        bbox=np.array(bbox, dtype=np.float64),
    )


def write_nemo_pascal3d(rng):
    """Angtian/NeMo layout: <root>/{images,annotations,lists}/car[FGLn_BGLn]/."""
    root = FIXTURES / "nemo_pascal3d"
    images, annos, lists = nemo_dirs(root, "car")
    for i, s in enumerate(NEMO_SAMPLES):
        name, d, p, bbox = s[0], s[4], s[5], s[6]
        crop, box, box_ori, box_obj, _, _ = nemo_crop(original_image(rng), p, d, bbox, CROP)
        save_jpeg(images / (name + ".JPEG"), crop)
        # MATLAB doubles: keypoint states come out as float64 (first sample), later ones as int64.
        visible = np.array([1.0, 0.0, 1.0]) if i == 0 else np.array([1, 1, 0])
        kps = [[4.5, 10.25], [0, 0], [9.0, 30.5]]
        np.savez(annos / name, name=name, box=box, box_ori=box_ori, box_obj=box_obj, cropped_kp_list=kps,
                 visible=visible, occ_mask=None, **mesh_params(s))
    # One list per subtype and one per CAD model; sample 0 appears in two of them.
    (lists / "sedan.txt").write_text(f"{NEMO_SAMPLES[2][0]}.JPEG\n{NEMO_SAMPLES[0][0]}.JPEG\n")
    (lists / "minivan.txt").write_text(f"{NEMO_SAMPLES[1][0]}.JPEG\n")
    (lists / "mesh01.txt").write_text(f"{NEMO_SAMPLES[1][0]}.JPEG\n")
    (lists / "mesh03.txt").write_text(f"{NEMO_SAMPLES[0][0]}.JPEG\n{NEMO_SAMPLES[2][0]}.JPEG\n")
    (lists / "mesh02.txt").write_text("")

    images, annos, lists = nemo_dirs(root, "carFGL1_BGL1")
    s = NEMO_SAMPLES[0]
    crop, box, box_ori, box_obj, _, _ = nemo_crop(original_image(rng), s[5], s[4], s[6], CROP)
    save_jpeg(images / (s[0] + ".JPEG"), crop)
    occ = np.zeros((48, 64), dtype=bool)  # the occluder mask of the *original* image, as NeMo stores it
    occ[20:30, 5:25] = True
    np.savez(annos / s[0], name=s[0], box=box, box_ori=box_ori, box_obj=box_obj, cropped_kp_list=[[4.5, 10.25]],
             visible=[0.0], occ_mask=occ, **mesh_params(s))
    (lists / "mesh03.txt").write_text(f"{s[0]}.JPEG\n")


def write_nemo_oodcv(rng):
    """OOD-CV-Pose layout: <root>/<split>/{images,annotations,lists}/car/, names <image>_<obj>."""
    images, annos, lists = nemo_dirs(FIXTURES / "nemo_oodcv" / "val", "car")
    names = []
    for s, nuisance in zip(NEMO_SAMPLES[:2], ("weather", "iid")):
        name = s[0] + "_00"
        names.append(name)
        crop, box, box_ori, box_obj, pad, rate = nemo_crop(original_image(rng), s[5], s[4], s[6], CROP)
        save_jpeg(images / (name + ".JPEG"), crop)
        params = mesh_params(s, int_dims=True)
        height, width = params.pop("height"), params.pop("width")
        padding = np.array([pad[0][0], pad[0][1], pad[1][0], pad[1][1], 0, 0])
        np.savez(annos / name, name=s[0], box=box, box_ori=box_ori, box_obj=box_obj, occ_mask=None, **params,
                 height=height, width=width, resize_rate=rate, padding_params=padding, nuisance=nuisance)
    (lists / "mesh01.txt").write_text(names[1])  # "\n".join: no trailing newline
    (lists / "mesh03.txt").write_text(names[0])


def write_nemo_nmm(rng):
    """neural-mesh-model layout: distance already 5, px/py already in the crop."""
    images, annos, lists = nemo_dirs(FIXTURES / "nemo_nmm" / "val", "car")
    s = NEMO_SAMPLES[2]
    name = s[0] + "_00"
    crop, box, box_ori, box_obj, pad, rate = nemo_crop(original_image(rng), s[5], s[4], s[6], CROP)
    save_jpeg(images / (name + ".JPEG"), crop)
    params = mesh_params(s, int_dims=True)
    height, width = params.pop("height"), params.pop("width")
    del params["distance"]
    np.savez(annos / name, name=s[0], box=box, box_ori=box_ori, box_obj=box_obj, occ_mask=None, amodal_mask=None,
             inmodal_mask=None, px=float(CROP[1] // 2), py=float(CROP[0] // 2), distance=5.0, **params,
             height=height, width=width, resize_rate=rate, padding_params=np.zeros(6, dtype=np.int64),
             true_cad_index=s[7], kp_weights=np.array([0.5, 1.0]), cropped_kp_list=np.array([[3.0, 4.0], [5.0, 6.0]]),
             visible=np.array([1, 0]))
    (lists / "mesh01.txt").write_text(name + "\n")


def check_rust():
    """np.load what the Rust tests wrote and compare with this script's arrays."""
    path = FIXTURES / "npz" / "rust_written.npz"
    expected = all_dtypes()
    with np.load(path, allow_pickle=True) as got:
        assert list(got.keys()) == list(expected.keys()), (list(got.keys()), list(expected.keys()))
        for key, want in expected.items():
            have = got[key]
            # Rust writes little-endian only: the big-endian array comes back as '<f8'.
            assert have.dtype == want.dtype.newbyteorder("<"), (key, have.dtype, want.dtype)
            assert have.shape == want.shape, (key, have.shape, want.shape)
            assert (have == want).all() if want.dtype != object else have.item() is None, key
    print(f"OK: numpy {np.__version__} reads {path.relative_to(FIXTURES.parent)} identically")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check-rust", action="store_true", help="verify the Rust-written npz with np.load")
    args = parser.parse_args()
    if args.check_rust:
        check_rust()
        return
    for sub in ("syncar", "nemo_pascal3d", "nemo_oodcv", "nemo_nmm"):
        shutil.rmtree(FIXTURES / sub, ignore_errors=True)
    rng = np.random.default_rng(20240501)
    write_npz_fixtures()
    write_syncar_fixtures(rng)
    write_nemo_pascal3d(rng)
    write_nemo_oodcv(rng)
    write_nemo_nmm(rng)
    total = sum(p.stat().st_size for p in FIXTURES.rglob("*") if p.is_file())
    print(f"wrote fixtures under {FIXTURES} ({total} bytes)")


if __name__ == "__main__":
    main()
