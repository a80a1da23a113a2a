//! Text labels drawn into RGB float images with a built-in 3×5 pixel font (capitals, digits and a few
//! signs; lower case is drawn as capitals, unknown characters as blanks), for comparison grids.

/// Glyph rows, top to bottom, three columns each ('#' set).
fn glyph(c: char) -> [&'static str; 5] {
    match c.to_ascii_uppercase() {
        'A' => [".#.", "#.#", "###", "#.#", "#.#"],
        'B' => ["##.", "#.#", "##.", "#.#", "##."],
        'C' => [".##", "#..", "#..", "#..", ".##"],
        'D' => ["##.", "#.#", "#.#", "#.#", "##."],
        'E' => ["###", "#..", "##.", "#..", "###"],
        'F' => ["###", "#..", "##.", "#..", "#.."],
        'G' => [".##", "#..", "#.#", "#.#", ".##"],
        'H' => ["#.#", "#.#", "###", "#.#", "#.#"],
        'I' => ["###", ".#.", ".#.", ".#.", "###"],
        'J' => ["..#", "..#", "..#", "#.#", ".#."],
        'K' => ["#.#", "#.#", "##.", "#.#", "#.#"],
        'L' => ["#..", "#..", "#..", "#..", "###"],
        'M' => ["#.#", "###", "###", "#.#", "#.#"],
        'N' => ["##.", "#.#", "#.#", "#.#", "#.#"],
        'O' => [".#.", "#.#", "#.#", "#.#", ".#."],
        'P' => ["##.", "#.#", "##.", "#..", "#.."],
        'Q' => [".#.", "#.#", "#.#", "##.", ".##"],
        'R' => ["##.", "#.#", "##.", "#.#", "#.#"],
        'S' => [".##", "#..", ".#.", "..#", "##."],
        'T' => ["###", ".#.", ".#.", ".#.", ".#."],
        'U' => ["#.#", "#.#", "#.#", "#.#", "###"],
        'V' => ["#.#", "#.#", "#.#", "#.#", ".#."],
        'W' => ["#.#", "#.#", "###", "###", "#.#"],
        'X' => ["#.#", "#.#", ".#.", "#.#", "#.#"],
        'Y' => ["#.#", "#.#", ".#.", ".#.", ".#."],
        'Z' => ["###", "..#", ".#.", "#..", "###"],
        '0' => ["###", "#.#", "#.#", "#.#", "###"],
        '1' => [".#.", "##.", ".#.", ".#.", "###"],
        '2' => ["##.", "..#", ".#.", "#..", "###"],
        '3' => ["##.", "..#", ".#.", "..#", "##."],
        '4' => ["#.#", "#.#", "###", "..#", "..#"],
        '5' => ["###", "#..", "##.", "..#", "##."],
        '6' => [".##", "#..", "###", "#.#", "###"],
        '7' => ["###", "..#", ".#.", ".#.", ".#."],
        '8' => ["###", "#.#", "###", "#.#", "###"],
        '9' => ["###", "#.#", "###", "..#", "##."],
        '.' => ["...", "...", "...", "...", ".#."],
        '-' => ["...", "...", "###", "...", "..."],
        ':' => ["...", ".#.", "...", ".#.", "..."],
        '%' => ["#.#", "..#", ".#.", "#..", "#.#"],
        '/' => ["..#", "..#", ".#.", "#..", "#.."],
        '=' => ["...", "###", "...", "###", "..."],
        '(' => [".#.", "#..", "#..", "#..", ".#."],
        ')' => [".#.", "..#", "..#", "..#", ".#."],
        _ => ["...", "...", "...", "...", "..."],
    }
}

/// Width in pixels of `text` drawn at `scale` (4 columns per character: 3 of glyph, 1 of space).
pub fn text_width(text: &str, scale: usize) -> usize {
    (4 * text.chars().count()).saturating_sub(1) * scale
}

/// Height in pixels of a line of text at `scale`.
pub fn text_height(scale: usize) -> usize {
    5 * scale
}

/// Draws `text` with its top-left corner at (x, y) into the `width`-wide row-major image `pixels`, each
/// font pixel a `scale`×`scale` square of `color`; what falls outside the image is clipped.
pub fn draw_text(
    pixels: &mut [[f32; 3]],
    width: usize,
    x: usize,
    y: usize,
    text: &str,
    scale: usize,
    color: [f32; 3],
) {
    let height = pixels.len() / width.max(1);
    for (i, c) in text.chars().enumerate() {
        for (row, bits) in glyph(c).iter().enumerate() {
            for (col, bit) in bits.bytes().enumerate() {
                if bit != b'#' {
                    continue;
                }
                for dy in 0..scale {
                    for dx in 0..scale {
                        let px = x + (4 * i + col) * scale + dx;
                        let py = y + row * scale + dy;
                        if px < width && py < height {
                            pixels[py * width + px] = color;
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

    #[test]
    fn text_is_drawn_inside_its_box_and_clipped_at_the_edges() {
        let (w, h) = (40, 12);
        let mut img = vec![[0.0f32; 3]; w * h];
        draw_text(&mut img, w, 1, 2, "NeRF 20", 1, [1.0; 3]);
        let lit: Vec<(usize, usize)> = (0..w * h)
            .filter(|&i| img[i][0] > 0.0)
            .map(|i| (i % w, i / w))
            .collect();
        assert!(!lit.is_empty());
        let right = 1 + text_width("NeRF 20", 1);
        assert!(lit
            .iter()
            .all(|&(x, y)| (1..right).contains(&x) && (2..2 + text_height(1)).contains(&y)));
        // Upper and lower case draw the same glyphs.
        let mut a = vec![[0.0f32; 3]; w * h];
        let mut b = vec![[0.0f32; 3]; w * h];
        draw_text(&mut a, w, 0, 0, "nerf", 2, [1.0; 3]);
        draw_text(&mut b, w, 0, 0, "NERF", 2, [1.0; 3]);
        assert_eq!(a, b);
        // Past the right and bottom edges: clipped, no panic.
        draw_text(&mut a, w, 35, 10, "WWWW", 3, [1.0; 3]);
    }
}
