//! The docs' contact sheet (docs/images/synth_contact_sheet.png) is made by
//! `aim synth --contact-sheet PATH`; set AIM_WRITE_CONTACT_SHEET=1 to regenerate it here.

use aim::synth::contact_sheet::{contact_sheet, OBJECTS_PER_ROW};
use aim::synth::OBJECT_NAMES;

fn tile_at(sheet: &image::RgbaImage, tile: u32, index: usize, state: usize) -> Vec<f32> {
    let gx = ((index % OBJECTS_PER_ROW) * 2 + state) as u32 * tile;
    let gy = (index / OBJECTS_PER_ROW) as u32 * tile;
    let mut v = Vec::with_capacity((tile * tile * 3) as usize);
    for y in 0..tile {
        for x in 0..tile {
            let p = sheet.get_pixel(gx + x, gy + y);
            v.extend([p[0] as f32, p[1] as f32, p[2] as f32]);
        }
    }
    v
}

#[test]
fn contact_sheet_shows_every_object_moving() {
    let tile = 64;
    let sheet = contact_sheet(tile).unwrap();
    let rows = OBJECT_NAMES.len().div_ceil(OBJECTS_PER_ROW) as u32;
    assert_eq!(sheet.dimensions(), (2 * OBJECTS_PER_ROW as u32 * tile, rows * tile));
    for (i, name) in OBJECT_NAMES.iter().enumerate() {
        let (a, b) = (tile_at(&sheet, tile, i, 0), tile_at(&sheet, tile, i, 1));
        let bg = a[0];
        let object_px = a.chunks(3).filter(|p| p.iter().any(|&c| (c - bg).abs() > 3.0)).count();
        assert!(object_px > 100, "{name}: start tile nearly empty ({object_px} px)");
        let changed =
            a.chunks(3).zip(b.chunks(3)).filter(|(p, q)| p.iter().zip(*q).any(|(x, y)| (x - y).abs() > 20.0)).count();
        assert!(changed > 20, "{name}: start and end tiles barely differ ({changed} px)");
    }
    let committed =
        std::path::PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR"))
            .join("docs/images/synth_contact_sheet.png");
    if std::env::var_os("AIM_WRITE_CONTACT_SHEET").is_some() {
        let big = contact_sheet(192).unwrap();
        big.save(&committed).unwrap();
    }
    let img = image::open(&committed).expect("docs/images/synth_contact_sheet.png (aim synth --contact-sheet)");
    assert_eq!(img.width(), 2 * OBJECTS_PER_ROW as u32 * 192);
    assert_eq!(img.height(), rows * 192);
}
