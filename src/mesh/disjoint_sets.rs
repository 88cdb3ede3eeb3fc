//! Union-find over indices: the connected parts of a mesh, the flat regions of a surface.

/// Union-find with path halving and union by size.
pub struct DisjointSets {
    parent: Vec<usize>,
    size: Vec<usize>,
}

impl DisjointSets {
    pub fn new(n: usize) -> Self {
        Self { parent: (0..n).collect(), size: vec![1; n] }
    }

    /// The representative of `i`'s set; `None` when `i` is out of range.
    pub fn find(&mut self, mut i: usize) -> Option<usize> {
        while *self.parent.get(i)? != i {
            let grandparent = self.parent[self.parent[i]];
            self.parent[i] = grandparent;
            i = grandparent;
        }
        Some(i)
    }

    pub fn union(&mut self, a: usize, b: usize) {
        let (Some(a), Some(b)) = (self.find(a), self.find(b)) else { return };
        if a == b {
            return;
        }
        let (big, small) = if self.size[a] >= self.size[b] { (a, b) } else { (b, a) };
        self.parent[small] = big;
        self.size[big] += self.size[small];
    }
}
