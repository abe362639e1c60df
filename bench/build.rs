include!("../engine/torch_link.rs");

fn main() {
    link_torch();
}
