//! `udapose-bench input`: what an estimate's input costs against one backbone pass, in this
//! process on one thread, as the service's worker computes it: decoding (full size, and at the
//! reduction `udapose_engine::input::max_reduction` allows) and cropping JPEGs of 320×128,
//! 1280×512 and 4000×3000, and a whole request with 1, 4 and 16 boxes. Writes
//! `reports/input.json` and its Markdown twin. Medians over `--repeats`; compare the ratios.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use serde_json::{Value, json};
use tch::Device;
use udapose_engine::checkpoint;
use udapose_engine::estimator::Estimator;
use udapose_engine::input::{self, Crop, CropBox, Rgb8Image};
use udapose_engine::solver::SolverConfig;
use udapose_lab::atomic::write_atomic;
use udapose_service::api::Pixels;
use udapose_service::decode::{DecodeLimits, Header};

use crate::harness::{git_commit, load_average, machine, median};

#[derive(clap::Args)]
pub struct InputArgs {
    /// Model directory (manifest.json + weights).
    #[arg(long, default_value = "models/car")]
    model: PathBuf,
    /// Timed runs per measurement (the median is reported).
    #[arg(long, default_value_t = 15)]
    repeats: usize,
    /// Report (JSON; a Markdown twin is written next to it).
    #[arg(long, default_value = "reports/input.json")]
    out: PathBuf,
    /// torch and rayon threads (the server's default is one per core).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u16).range(1..))]
    threads: u16,
    /// The batched row's backbone passes: at most this many boxes each (the server's
    /// --max-batch default).
    #[arg(long, default_value_t = 8)]
    max_batch: usize,
    /// Also writes each test image here (e.g. to time another decoder on the same files:
    /// lab/scripts/libjpeg_turbo_input.py).
    #[arg(long)]
    save_images: Option<PathBuf>,
}

/// A photograph-like test image: smooth shading, edges and ±`noise` levels of sensor-like noise
/// (at 12, a JPEG of it is as large, and as costly to entropy-decode, as a camera's: ~5 MB at
/// 12 MP), encoded as `format` (JPEG at quality 90).
fn photo(width: u32, height: u32, noise_levels: f64, format: image::ImageFormat) -> Result<Vec<u8>> {
    let mut state = 0x2545_F491_4F6C_DD1Du64;
    let mut noise = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        ((state >> 56) as f64 / 255.0 * 2.0 - 1.0) * noise_levels
    };
    let image = image::RgbImage::from_fn(width, height, |x, y| {
        let (u, v) = (x as f64 / width as f64, y as f64 / height as f64);
        let edge = if ((u * 9.0).floor() + (v * 5.0).floor()) % 2.0 == 0.0 { 40.0 } else { 0.0 };
        image::Rgb(std::array::from_fn(|c| {
            let shade = 110.0 + 60.0 * ((u * 7.0 + c as f64).sin() * (v * 4.0).cos());
            (shade + edge + noise()).clamp(0.0, 255.0) as u8
        }))
    });
    let mut out = Vec::new();
    if format == image::ImageFormat::Jpeg {
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 90).encode_image(&image)?;
    } else {
        image.write_to(&mut std::io::Cursor::new(&mut out), format)?;
    }
    Ok(out)
}

/// Median milliseconds of `f` over `repeats` runs after one untimed run.
fn time_ms<T>(repeats: usize, mut f: impl FnMut() -> Result<T>) -> Result<f64> {
    f()?;
    let mut ms = Vec::with_capacity(repeats);
    for _ in 0..repeats {
        let t = Instant::now();
        std::hint::black_box(f()?);
        ms.push(t.elapsed().as_secs_f64() * 1e3);
    }
    Ok(median(&ms))
}

fn crops(pixels: &Pixels, boxes: &[CropBox], size: [usize; 2]) -> Result<Vec<Crop>> {
    let [ew, eh] = pixels.encoded;
    let image = Rgb8Image::new(&pixels.rgb8, pixels.width, pixels.height)?.decoded_from(ew, eh)?;
    if boxes.is_empty() {
        return Ok(vec![input::crop(&image, None, size)?]);
    }
    boxes.iter().map(|&b| Ok(input::crop(&image, Some(b), size)?)).collect()
}

pub fn run(args: &InputArgs) -> Result<()> {
    tch::set_num_threads(args.threads as i32);
    let pool = rayon::ThreadPoolBuilder::new().num_threads(args.threads as usize).build()?;
    pool.install(|| measure(args))
}

fn measure(args: &InputArgs) -> Result<()> {
    let model =
        checkpoint::load(&args.model, Device::Cpu).with_context(|| format!("loading {}", args.model.display()))?;
    let estimator = Estimator::new(model, SolverConfig::default())?;
    let size = estimator.model.manifest.crop;
    let limits = DecodeLimits::default();
    let (n, started) = (args.repeats, Instant::now());

    let first = photo(size[1] as u32, size[0] as u32, 12.0, image::ImageFormat::Jpeg)?;
    let first_crop = crops(&Header::read(&first, limits)?.decode(&first, limits)?, &[], size)?.remove(0);
    let backbone_ms = time_ms(n, || Ok(estimator.batch_features(&first_crop.tensor())?))?;
    eprintln!("backbone pass: {backbone_ms:.1} ms");

    let mut sizes = Vec::new();
    let (jpeg, png) = (image::ImageFormat::Jpeg, image::ImageFormat::Png);
    let (cw, ch) = (size[1] as u32, size[0] as u32);
    let images = [
        (cw, ch, 12.0, jpeg),
        (1280, 512, 12.0, jpeg),
        (4000, 3000, 12.0, jpeg),
        (4000, 3000, 0.0, jpeg),
        (4000, 3000, 12.0, png),
    ];
    for (w, h, noise, format) in images {
        let bytes = photo(w, h, noise, format)?;
        if let Some(dir) = &args.save_images {
            let ext = format.extensions_str()[0];
            std::fs::create_dir_all(dir)?;
            write_atomic(&dir.join(format!("{w}x{h}-noise{noise}.{ext}")), &bytes)?;
        }
        let header = Header::read(&bytes, limits)?;
        let r = input::max_reduction(w as usize, h as usize, &[], size);
        let name = format!("{w}x{h} {}", format.extensions_str()[0].to_uppercase());
        let mut row = json!({"image": name, "noise": noise, "jpeg_bytes": bytes.len(), "reduction": r});
        for (key, r) in [("full", 1), ("reduced", r)] {
            let decode_ms = time_ms(n, || Ok(header.decode_for(&bytes, limits, r)?))?;
            let pixels = header.decode_for(&bytes, limits, r)?;
            let crop_ms = time_ms(n, || crops(&pixels, &[], size))?;
            row[key] = json!({"decode_ms": decode_ms, "crop_ms": crop_ms, "ms": decode_ms + crop_ms});
        }
        let (full, reduced) = (row["full"]["ms"].as_f64().unwrap_or(0.0), row["reduced"]["ms"].as_f64().unwrap_or(0.0));
        row["decode_crop_over_backbone"] = json!(reduced / backbone_ms);
        row["speedup"] = json!(full / reduced);
        eprintln!("{name}, noise {noise}: full {full:.1} ms, at 1/{r} {reduced:.1} ms");
        sizes.push(row);
    }

    // A whole request on a 1280×512 frame: decode, crops, the backbone over the boxes (one pass
    // per box, or passes of up to max_batch) and one solve per box.
    let frame = photo(1280, 512, 12.0, image::ImageFormat::Jpeg)?;
    let header = Header::read(&frame, limits)?;
    let mut per_boxes = Vec::new();
    for k in [1usize, 4, 16] {
        let boxes: Vec<CropBox> = (0..k)
            .map(|i| {
                let (x0, y0) = (40.0 + 70.0 * (i % 8) as f64, 40.0 + 200.0 * (i / 8) as f64);
                CropBox { x0, y0, x1: x0 + 600.0, y1: y0 + 240.0 }
            })
            .collect();
        let r = input::max_reduction(1280, 512, &boxes, size);
        let mut row = json!({"boxes": k});
        for (key, max_batch) in [("ms", 1), ("batched_ms", args.max_batch)] {
            let ms = time_ms(n.div_ceil(k).max(3), || {
                let crops = crops(&header.decode_for(&frame, limits, r)?, &boxes, size)?;
                let refs: Vec<&Crop> = crops.iter().collect();
                let features = estimator.features(&refs, max_batch)?;
                Ok(estimator.estimate_all(&refs, &features).into_iter().collect::<Result<Vec<_>, _>>()?)
            })?;
            eprintln!("{k} boxes, passes of {max_batch}: {ms:.1} ms");
            row[key] = json!(ms);
        }
        per_boxes.push(row);
    }
    let one = per_boxes[0]["ms"].as_f64().unwrap_or(f64::NAN);
    for row in &mut per_boxes {
        for (key, over) in [("ms", "over_one_box"), ("batched_ms", "batched_over_one_box")] {
            let ratio = row[key].as_f64().unwrap_or(f64::NAN) / one;
            row[over] = json!(ratio);
        }
    }

    let report = json!({
        "model": estimator.model.manifest.version, "backbone": estimator.model.manifest.backbone,
        "crop": size, "threads": args.threads, "max_batch": args.max_batch, "repeats": n, "machine": machine(), "commit": git_commit(),
        "load_average_after": load_average(), "seconds": started.elapsed().as_secs_f64(),
        "backbone_ms": backbone_ms, "sizes": sizes, "boxes": per_boxes,
    });
    write_atomic(&args.out, (serde_json::to_string_pretty(&report)? + "\n").as_bytes())?;
    write_atomic(&args.out.with_extension("md"), markdown(&report).as_bytes())?;
    eprintln!("wrote {} and its .md", args.out.display());
    Ok(())
}

fn markdown(r: &Value) -> String {
    let f = |v: &Value| v.as_f64().unwrap_or(f64::NAN);
    let mut md = format!(
        "# Input cost against the backbone\n\n`udapose-bench input --model <dir>` (`{}`, {}, crop {}×{}), commit `{}`, {} \
         (torch and rayon); medians of {} runs; load average after: {}.\n\n\
         One backbone pass (batch 1): **{:.1} ms**.\n\n\
         Photograph-like images (JPEG at quality 90; noise: ± levels of sensor-like noise, 12 giving a camera's file \
         size). *Full*: decoded at full size, then cropped (the whole image, padded to the crop's aspect). *Reduced*: \
         kept at 1/r, r the largest that keeps the crop's region at least the crop's size (`input::max_reduction`): a \
         JPEG decoded so by its DCT scaling, a PNG decoded whole then shrunk by block means; then cropped.\n\n\
         | image | noise | file | full: decode + crop (ms) | r | reduced: decode + crop (ms) | reduced / backbone | speed-up |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|\n",
        r["model"].as_str().unwrap_or(""),
        r["backbone"].as_str().unwrap_or(""),
        r["crop"][0],
        r["crop"][1],
        r["commit"].as_str().unwrap_or(""),
        r["machine"].as_str().unwrap_or(""),
        r["repeats"],
        r["load_average_after"].as_str().unwrap_or(""),
        f(&r["backbone_ms"]),
    );
    for s in r["sizes"].as_array().into_iter().flatten() {
        md += &format!(
            "| {} | {} | {} KB | {:.1} + {:.1} | {} | {:.1} + {:.1} | {:.0}% | {:.1}× |\n",
            s["image"].as_str().unwrap_or(""),
            s["noise"],
            s["jpeg_bytes"].as_u64().unwrap_or(0) / 1000,
            f(&s["full"]["decode_ms"]),
            f(&s["full"]["crop_ms"]),
            s["reduction"],
            f(&s["reduced"]["decode_ms"]),
            f(&s["reduced"]["crop_ms"]),
            100.0 * f(&s["decode_crop_over_backbone"]),
            f(&s["speedup"]),
        );
    }
    md += &format!(
        "\nA whole request on a 1280×512 JPEG frame with k boxes of 600×240: decode, crops, the backbone (one pass \
         per box as `--max-batch 1` runs it, or passes of up to {} boxes as the server's default does), a solve per \
         box. × one box: against one box's request.\n\n\
         | boxes | one pass per box (ms) | × one box | passes of {} (ms) | × one box |\n|---:|---:|---:|---:|---:|\n",
        r["max_batch"], r["max_batch"]
    );
    for b in r["boxes"].as_array().into_iter().flatten() {
        md += &format!(
            "| {} | {:.1} | {:.2} | {:.1} | {:.2} |\n",
            b["boxes"],
            f(&b["ms"]),
            f(&b["over_one_box"]),
            f(&b["batched_ms"]),
            f(&b["batched_over_one_box"])
        );
    }
    md
}
