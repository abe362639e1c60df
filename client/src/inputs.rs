//! The CLI's inputs: image files and folders, stdin, boxes.

use std::io::Read;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use udapose_client::BoundingBox;

use crate::output::is_image;

/// Files as given; folders become their images (sorted); `-` is stdin.
pub fn expand(inputs: &[PathBuf]) -> Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    for input in inputs {
        if input.is_dir() {
            let mut images: Vec<PathBuf> = std::fs::read_dir(input)
                .with_context(|| format!("listing {}", input.display()))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| is_image(p))
                .collect();
            images.sort();
            if images.is_empty() {
                bail!("{} holds no PNG, JPEG or WebP files", input.display());
            }
            out.extend(images);
        } else {
            out.push(input.clone());
        }
    }
    Ok(out)
}

pub fn read_input(path: &Path) -> Result<Vec<u8>> {
    if path == Path::new("-") {
        let mut bytes = Vec::new();
        std::io::stdin().read_to_end(&mut bytes).context("reading stdin")?;
        return Ok(bytes);
    }
    std::fs::read(path).with_context(|| format!("reading {}", path.display()))
}

pub fn parse_box(s: &str) -> Result<BoundingBox, String> {
    let v: Vec<f64> =
        s.split(',').map(|x| x.trim().parse::<f64>()).collect::<Result<_, _>>().map_err(|e| e.to_string())?;
    match v.as_slice() {
        [x0, y0, x1, y1] => Ok(BoundingBox { x0: *x0, y0: *y0, x1: *x1, y1: *y1 }),
        _ => Err(format!("expected x0,y0,x1,y1, got {s:?}")),
    }
}
