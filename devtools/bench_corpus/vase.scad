// a vase for spiral mode: a twisted, flaring 7-lobed shell, 60 mm tall
linear_extrude(height = 60, twist = 90, slices = 120, scale = 1.4)
  offset(r = 3) circle(r = 17, $fn = 7);
