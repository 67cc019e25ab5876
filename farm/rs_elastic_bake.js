// SPDX-License-Identifier: GPL-3.0-or-later
//
// RS Elastic Bake: a Flamenco job type that bakes the RS Elastic bodies of a shot, one task per
// body, each after the bodies whose bakes it reads, then collects the bakes into the shot.
//
// Install: put this file in the `scripts` folder beside `flamenco-manager` (RS Elastic's
// "Write Flamenco Job Type…" button does it), then refresh the job types in Blender's Flamenco
// panel. The workers need Blender with the RS Elastic extension installed and enabled.
//
// At submission the Flamenco add-on evaluates `bodies` in the artist's Blender: the extension's
// plan of the shot (bridge/farm.py), {"bodies": [{name, mode, frames, after, bake_file}]} in an
// order where every body comes after the bodies in its `after`, or {"error": "..."}. `bake_file`
// is the Mesh Cache file the body's task writes (a new name at each submission, in the shot's
// bakes folder): the tasks that read that bake, and the last one, which collects every bake into
// the shot, are given it.

const JOB_TYPE = {
    label: "RS Elastic Bake",
    description: "Prepare and bake the shot's RS Elastic bodies, one task per body, in the order their bakes feed each other",
    settings: [
        { key: "steps", type: "string", required: true, visible: "submission",
          choices: ["prepare and bake", "prepare only", "bake only"], default: "prepare and bake",
          description: "Prepare and bake (what the command line does), prepare only (fills the cache next to the shot), or bake only (prepares nothing: a body whose preparation is not in the shot and its cache fails)" },
        { key: "bodies", type: "string", required: true, visible: "web",
          eval: "C.scene.rs_elastic_farm.plan",
          description: "The shot's bodies, how each is baked and whose bakes it reads (JSON, from the RS Elastic extension)" },
        { key: "blendfile", type: "string", required: true, visible: "web",
          description: "The shot on the shared storage; the bakes are written next to it" },
    ]
};

const STEPS = {
    "prepare and bake": { verb: "bake", args: [], collect: true },
    "prepare only": { verb: "prepare", args: ["--only", "prepare"], collect: false },
    "bake only": { verb: "bake", args: ["--only", "bake"], collect: true },
};

function compileJob(job) {
    const settings = job.settings;
    const step = STEPS[settings.steps];
    if (!step) {
        throw `unknown steps "${settings.steps}": one of ${Object.keys(STEPS).join(", ")}`;
    }
    const bodies = readPlan(settings.bodies);

    // Tasks run in the plan's order when workers are few: priorities fall along it.
    const tasks = {};
    const files = {};
    for (const body of bodies) {
        files[body.name] = body.bake_file;
    }
    bodies.forEach((body, index) => {
        const task = author.Task(`${step.verb} ${body.name}`, "blender");
        task.priority = 50 + bodies.length - index;
        // NAME=VALUE, so that a name starting with "-" is not taken for an option.
        const args = [`--object=${body.name}`].concat(step.args);
        if (step.verb == "bake") {
            args.push("--mode", body.mode, "--frames", body.frames, "--bake-to", "cache",
                      `--bake-file=${body.bake_file}`);
            for (const name of body.after) {
                args.push(`--with-bake=${name}=${files[name]}`);
                task.addDependency(tasks[name]);
            }
        }
        args.push("--no-save");
        task.addCommand(blenderCommand(settings.blendfile, ["bake"].concat(args)));
        job.addTask(task);
        tasks[body.name] = task;
    });

    if (step.collect) {
        const collect = author.Task("collect bakes", "blender");
        collect.priority = 50;
        let args = ["collect"];
        for (const body of bodies) {
            args.push(`--bake=${body.name}=${body.bake_file}`);
            collect.addDependency(tasks[body.name]);
        }
        collect.addCommand(blenderCommand(settings.blendfile, args));
        job.addTask(collect);
    }
}

// The plan evaluated at submission, checked: every body it names comes before its dependents.
function readPlan(text) {
    let plan;
    try {
        plan = JSON.parse(text);
    } catch (error) {
        throw `the bodies setting is not the RS Elastic plan (is the extension enabled where the job was submitted?): ${error}`;
    }
    if (plan.error) {
        throw plan.error;
    }
    if (!plan.bodies || plan.bodies.length == 0) {
        throw "the shot has no RS Elastic bodies: tetrahedralize or prepare a body first";
    }
    const seen = new Set();
    for (const body of plan.bodies) {
        if (!body.bake_file) {
            throw `the plan names no bake file for "${body.name}" (an older RS Elastic submitted it?)`;
        }
        for (const name of body.after) {
            if (!seen.has(name)) {
                throw `the plan lists "${body.name}" before "${name}", whose bake it reads`;
            }
        }
        seen.add(body.name);
    }
    return plan.bodies;
}

function blenderCommand(blendfile, args) {
    return author.Command("blender-render", {
        exe: "{blender}",
        exeArgs: "{blenderArgs}",
        argsBefore: [],
        blendfile: blendfile,
        args: ["-c", "rs_elastic"].concat(args),
    });
}
