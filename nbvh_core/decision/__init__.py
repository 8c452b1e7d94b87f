"""Every decision a run makes about what to train and what to ship, from measurements: the alternative's curve
(`alternative_curve`), the rule at each training check (`checks`: stop, grow, keep the mesh), and the final verdict
after the held-out evaluation (`final_verdict`). Each decision is a typed record (`records`)."""
