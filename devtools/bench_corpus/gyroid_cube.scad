// a 30 x 30 x 12 mm block for fast gyroid infill (wavy lines of short segments)
cube([30, 30, 12]);
