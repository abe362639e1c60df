//! The training loader: every sample once per epoch, seeded order, pixels and poses as stored.

use std::collections::BTreeSet;
use std::path::PathBuf;

use udapose_lab::datasets::syncar::SyncarSplit;
use udapose_lab::loader::Loader;

fn quick_data() -> PathBuf {
    // `make test` renders the quick dataset once per run; the synth tests check it.
    PathBuf::from(std::env::var_os("UDAPOSE_QUICK_DATA").expect("UDAPOSE_QUICK_DATA is set by `make test`"))
}

#[test]
fn an_epoch_yields_every_sample_once_in_a_seeded_order() {
    let split = SyncarSplit::open(&quick_data(), "source", "val").unwrap();
    let n = split.len();
    let order = |seed| {
        let mut loader = Loader::new(split.clone(), 16, 2, seed).unwrap();
        let epochs: Vec<Vec<String>> =
            (0..2).map(|_| loader.epoch().flat_map(|b| b.unwrap().names).collect()).collect();
        epochs
    };
    let a = order(7);
    assert_eq!(a[0].len(), n);
    assert_eq!(a[0].iter().collect::<BTreeSet<_>>().len(), n, "each sample once");
    assert_ne!(a[0], a[1], "a new order each epoch");
    assert_eq!(a, order(7), "the same seed gives the same orders");
    assert_ne!(a[0], order(8)[0]);
}

/// A run resumed within an epoch reads the rest of the very order it was interrupted in.
#[test]
fn an_epoch_started_at_a_batch_continues_the_same_order() {
    let split = SyncarSplit::open(&quick_data(), "source", "val").unwrap();
    let names = |first: usize| {
        let mut loader = Loader::new(split.clone(), 16, 2, 7).unwrap();
        drop(loader.epoch());
        loader.epoch_from(first).flat_map(|b| b.unwrap().names).collect::<Vec<String>>()
    };
    let whole = names(0);
    assert_eq!(names(2), whole[32..]);
    assert!(names(whole.len()).is_empty());
}

#[test]
fn batches_hold_planar_pixels_and_the_stored_poses() {
    let split = SyncarSplit::open(&quick_data(), "source", "val").unwrap();
    let mut loader = Loader::new(split.clone(), 16, 1, 0).unwrap();
    let batches: Vec<_> = loader.epoch().map(|b| b.unwrap()).collect();
    assert_eq!(batches.iter().map(|b| b.len()).collect::<Vec<_>>(), vec![16, 16, 16, 12]);
    let b = &batches[0];
    assert_eq!((b.height, b.width, b.images.len()), (64, 160, 16 * 3 * 64 * 160));
    assert!(b.images.iter().all(|v| (0.0..=1.0).contains(v)));
    let index = split.entries().iter().position(|e| e.name == b.names[3]).unwrap();
    let sample = split.load(index).unwrap();
    assert_eq!(b.poses[3], sample.annotation.pose.pose());
    let img = image::open(&sample.entry.image_path).unwrap().to_rgb8();
    let (x, y) = (77, 31);
    let plane = 64 * 160;
    let at = 3 * 3 * plane + y * 160 + x;
    assert_eq!(b.images[at + plane], img.get_pixel(x as u32, y as u32).0[1] as f32 / 255.0, "green plane");
}

#[test]
fn empty_splits_and_zero_batches_are_errors() {
    let split = SyncarSplit::open(&quick_data(), "source", "val").unwrap();
    assert!(Loader::new(split, 0, 1, 0).is_err());
    assert!(SyncarSplit::open(&quick_data(), "source", "nope").is_err());
}
