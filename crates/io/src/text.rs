//! Text on images with a small built-in bitmap font (5×7 glyphs drawn with 2× pixels, 12
//! pixels per character): plot labels and the numbers printed on contact sheets, without a
//! font file or a font crate.

use crate::Image;

/// 5×7 glyphs (one byte per row, low 5 bits, MSB left) for the characters plots need.
fn glyph(ch: char) -> [u8; 7] {
    match ch {
        '0' => [14, 17, 19, 21, 25, 17, 14],
        '1' => [4, 12, 4, 4, 4, 4, 14],
        '2' => [14, 17, 1, 2, 4, 8, 31],
        '3' => [31, 2, 4, 2, 1, 17, 14],
        '4' => [2, 6, 10, 18, 31, 2, 2],
        '5' => [31, 16, 30, 1, 1, 17, 14],
        '6' => [6, 8, 16, 30, 17, 17, 14],
        '7' => [31, 1, 2, 4, 8, 8, 8],
        '8' => [14, 17, 17, 14, 17, 17, 14],
        '9' => [14, 17, 17, 15, 1, 2, 12],
        '.' => [0, 0, 0, 0, 0, 12, 12],
        '-' => [0, 0, 0, 31, 0, 0, 0],
        '_' => [0, 0, 0, 0, 0, 0, 31],
        ':' => [0, 12, 12, 0, 12, 12, 0],
        'a' => [0, 0, 14, 1, 15, 17, 15],
        'b' => [16, 16, 22, 25, 17, 17, 30],
        'c' => [0, 0, 14, 16, 16, 17, 14],
        'd' => [1, 1, 13, 19, 17, 17, 15],
        'e' => [0, 0, 14, 17, 31, 16, 14],
        'f' => [6, 9, 8, 28, 8, 8, 8],
        'g' => [0, 15, 17, 17, 15, 1, 14],
        'h' => [16, 16, 22, 25, 17, 17, 17],
        'i' => [4, 0, 12, 4, 4, 4, 14],
        'j' => [2, 0, 6, 2, 2, 18, 12],
        'k' => [16, 16, 18, 20, 24, 20, 18],
        'l' => [12, 4, 4, 4, 4, 4, 14],
        'm' => [0, 0, 26, 21, 21, 17, 17],
        'n' => [0, 0, 22, 25, 17, 17, 17],
        'o' => [0, 0, 14, 17, 17, 17, 14],
        'p' => [0, 0, 30, 17, 30, 16, 16],
        'q' => [0, 0, 13, 19, 15, 1, 1],
        'r' => [0, 0, 22, 25, 16, 16, 16],
        's' => [0, 0, 14, 16, 14, 1, 30],
        't' => [8, 8, 28, 8, 8, 9, 6],
        'u' => [0, 0, 17, 17, 17, 19, 13],
        'v' => [0, 0, 17, 17, 17, 10, 4],
        'w' => [0, 0, 17, 17, 21, 21, 10],
        'x' => [0, 0, 17, 10, 4, 10, 17],
        'y' => [0, 0, 17, 17, 15, 1, 14],
        'z' => [0, 0, 31, 2, 4, 8, 31],
        _ => [0; 7],
    }
}

/// Draws `text` (lower case, digits, `.-_:`) at `(x, y)` with 2× pixels.
pub fn draw_text(img: &mut Image, text: &str, x: usize, y: usize, colour: [f32; 3]) {
    for (k, ch) in text.to_lowercase().chars().enumerate() {
        let rows = glyph(ch);
        for (j, row) in rows.iter().enumerate() {
            for i in 0..5 {
                if row & (1 << (4 - i)) != 0 {
                    for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                        let (px, py) = (x + 12 * k + 2 * i + dx, y + 2 * j + dy);
                        if px < img.width && py < img.height {
                            img.pixel_mut(px, py)[..3].copy_from_slice(&colour);
                        }
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A glyph's pixels land in its 12-pixel cell, a space draws nothing, and text past the
    /// image's edge is clipped rather than a panic.
    #[test]
    fn text_draws_glyphs_in_their_cells_and_clips_at_the_edge() {
        let mut img = Image::filled(30, 16, 3, 0.0);
        draw_text(&mut img, " 1", 0, 0, [1.0, 0.0, 0.0]);
        let lit = |x0: usize, x1: usize| {
            (0..16)
                .flat_map(|y| (x0..x1).map(move |x| (x, y)))
                .filter(|&(x, y)| img.pixel(x, y)[0] == 1.0)
                .count()
        };
        assert_eq!(lit(0, 12), 0, "a space draws nothing");
        // '1' has 1 + 2 + 1 + 1 + 1 + 1 + 3 = 10 pixels, each drawn 2 × 2.
        assert_eq!(lit(12, 24), 4 * 10);
        draw_text(&mut img, "88888", 20, 10, [0.0, 1.0, 0.0]);
    }
}
