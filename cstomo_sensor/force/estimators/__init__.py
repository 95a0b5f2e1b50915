"""The force estimators (linear, model), their training data and thin-plate spline, the joint fit of force and
scale, and the small linear algebra they share."""
