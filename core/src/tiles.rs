//! The tile grid: how an image is cut into tiles and how the tiles are numbered, defined
//! once for `dray render`, the coordinator and the workers (docs/architecture.md
//! "Words": Tile).
//!
//! Tiles are squares of `size` pixels (edge tiles smaller), numbered row-major: the tile
//! holding pixel `(x, y)` is `(y / size) * tiles_x + x / size`. The coordinator deals
//! tiles by that number, a worker finds the tile of every ray it hands credit back for by
//! it, and a ray-cache coarse pass numbers its own grid after the image's.
//!
//! Counts and indices are `u32`, as the wire's tile index is: every image the
//! coordinator and the workers accept (at most 16384 pixels a side) has fewer than 2^28
//! tiles even with 1-pixel tiles.

/// Tile edge in pixels of every job: `dray render`'s tiles and the coordinator's
/// (`JobSetup.tile_size`), so progress reads the same.
pub const TILE_SIZE: u32 = 32;

/// A rectangle of pixels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Tile {
    pub x0: u32,
    pub y0: u32,
    pub w: u32,
    pub h: u32,
}

/// A `width` x `height` image cut into tiles of at most `size` pixels a side.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileGrid {
    width: u32,
    height: u32,
    size: u32,
    /// Tiles per row and per column, kept: a worker finds a ray's tile per ray.
    tiles_x: u32,
    tiles_y: u32,
}

impl TileGrid {
    /// The grid of a `width` x `height` image with `size`-pixel tiles (a size of 0 is
    /// taken as 1). An image with no pixels has no tiles.
    pub fn new(width: u32, height: u32, size: u32) -> TileGrid {
        let size = size.max(1);
        TileGrid {
            width,
            height,
            size,
            tiles_x: width.div_ceil(size),
            tiles_y: height.div_ceil(size),
        }
    }

    /// The grid of a `width` x `height` image with [`TILE_SIZE`] tiles.
    pub fn image(width: u32, height: u32) -> TileGrid {
        TileGrid::new(width, height, TILE_SIZE)
    }

    /// Tile edge in pixels.
    pub fn size(&self) -> u32 {
        self.size
    }

    /// Tiles in all.
    pub fn count(&self) -> u32 {
        self.tiles_x * self.tiles_y
    }

    /// The index of the tile holding pixel `(x, y)`.
    #[inline]
    pub fn index_of(&self, x: u32, y: u32) -> u32 {
        (y / self.size) * self.tiles_x + x / self.size
    }

    /// The index of the tile holding pixel `pixel`, numbered row-major over the image
    /// (`y * width + x`).
    #[inline]
    pub fn index_of_pixel(&self, pixel: u32) -> u32 {
        let w = self.width.max(1);
        self.index_of(pixel % w, pixel / w)
    }

    /// The rectangle of tile `i`, `None` past the last tile.
    pub fn rect(&self, i: u32) -> Option<Tile> {
        if i >= self.count() {
            return None;
        }
        let (x0, y0) = (
            (i % self.tiles_x) * self.size,
            (i / self.tiles_x) * self.size,
        );
        Some(Tile {
            x0,
            y0,
            w: self.size.min(self.width - x0),
            h: self.size.min(self.height - y0),
        })
    }

    /// Every tile, in index order.
    pub fn iter(&self) -> impl ExactSizeIterator<Item = Tile> + '_ {
        (0..self.count()).map(|i| self.rect(i).expect("an index below the count"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiles_cover_the_image_row_major_with_the_documented_index() {
        let g = TileGrid::new(70, 40, 32);
        assert_eq!(g.count(), 3 * 2);
        let tiles: Vec<Tile> = g.iter().collect();
        assert_eq!(tiles.len(), 6);
        for (i, t) in tiles.iter().enumerate() {
            assert_eq!(g.index_of(t.x0, t.y0), i as u32);
            assert_eq!(g.index_of(t.x0 + t.w - 1, t.y0 + t.h - 1), i as u32);
            assert_eq!(g.rect(i as u32), Some(*t));
        }
        assert_eq!(
            tiles[0],
            Tile {
                x0: 0,
                y0: 0,
                w: 32,
                h: 32
            }
        );
        assert_eq!((tiles[2].w, tiles[2].h), (6, 32));
        assert_eq!(
            tiles[5],
            Tile {
                x0: 64,
                y0: 32,
                w: 6,
                h: 8
            }
        );
        assert_eq!(g.rect(6), None);
        let px: u32 = tiles.iter().map(|t| t.w * t.h).sum();
        assert_eq!(px, 70 * 40);
        // Pixel 70 * 35 + 65 is (65, 35), in the last tile.
        assert_eq!(g.index_of_pixel(70 * 35 + 65), 5);
    }

    #[test]
    fn every_pixel_is_in_the_tile_its_index_names() {
        for (w, h, s) in [(1, 1, 32), (33, 17, 8), (64, 64, 32), (5, 9, 1), (7, 3, 0)] {
            let g = TileGrid::new(w, h, s);
            for (i, t) in g.iter().enumerate() {
                for y in t.y0..t.y0 + t.h {
                    for x in t.x0..t.x0 + t.w {
                        assert_eq!(g.index_of_pixel(y * w + x), i as u32, "{w}x{h}/{s}");
                    }
                }
            }
        }
    }

    #[test]
    fn an_empty_image_has_no_tiles() {
        for g in [
            TileGrid::new(0, 0, 32),
            TileGrid::new(0, 10, 32),
            TileGrid::image(10, 0),
        ] {
            assert_eq!(g.count(), 0);
            assert_eq!(g.iter().count(), 0);
        }
    }
}
