"""Every decision a run makes about what to train and what to ship, from measurements, each a rule on numbers
handed in (measurements, predictions, byte counts) and each answered as a typed record (`records`):

    verdict        before training: is the model worth training against the mesh and its measured decimation?
    growth         the growing training's plan: start and largest table, clock, check period
    checks         at each training check: train on, grow, roll back, stop (level met), stop and keep the mesh
    size_search    the "retrain" search: predict a size, train, measure, correct
    final_verdict  after the held-out evaluation: the model as shipped against the alternative at its own MSE
    scene_budget   a scene's byte budget shared among its objects by need

`alternative_curve` is the measured alternative (bytes against MSE) the checks and the final verdict weigh against;
`config.DecisionConfig` is what a run asks of them."""
