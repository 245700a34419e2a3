// `lifemap models ...`: the random-forest models the server labels frames with.
#include <iostream>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "client/cli/commands.h"
#include "client/cli/output.h"
#include "core/common/image_codec.h"

namespace lifemap::cli {
namespace {

std::string Where(const std::string& map) {
  return map.empty() ? std::string("the server default") : absl::StrCat("map '", map, "'");
}

void PrintModel(const v1::ModelInfo& m) {
  std::vector<std::string> active(m.active_maps().begin(), m.active_maps().end());
  if (m.is_default()) active.insert(active.begin(), "server default");
  std::cout << absl::StrFormat(
      "%-24s %9s %2d trees %8d nodes  %s  [%s]  %s\n", m.name(), HumanBytes(m.size_bytes()),
      m.trees(), m.nodes(), HumanTime(m.uploaded_time_s()), absl::StrJoin(m.class_names(), ", "),
      active.empty() ? "inactive" : "active: " + absl::StrJoin(active, ", "));
}

}  // namespace

void AddModelCommands(CLI::App* app, CliContext* ctx) {
  auto* models = app->add_subcommand(
      "models", "Upload, list, activate and delete the server's object-class models");
  models->require_subcommand(1);

  auto* upload = models->add_subcommand("upload", "Upload a model file (from lifemap train)");
  auto file = std::make_shared<std::string>();
  auto name = std::make_shared<std::string>();
  upload->add_option("FILE", *file, "model file")->required()->check(CLI::ExistingFile);
  upload->add_option("NAME", *name, "name on the server (letters, digits, . _ -)")->required();
  upload->callback([ctx, file, name] {
    ctx->run = [ctx, file, name] {
      auto bytes = ReadFileBytes(*file);
      if (!bytes.ok()) return Fail(bytes.status());
      return RunCall<v1::ModelInfo>(
          *ctx, [&](client::Client& c) { return c.UploadModel(*name, *bytes); },
          [](const v1::ModelInfo& m) {
            std::cout << "uploaded ";
            PrintModel(m);
            std::cout << "activate it with: lifemap models activate " << m.name() << " [MAP]\n";
          });
    };
  });

  models->add_subcommand("list", "List stored models and where they are active")->callback([ctx] {
    ctx->run = [ctx] {
      return RunCall<v1::ListModelsResponse>(
          *ctx, [](client::Client& c) { return c.ListModels(); },
          [](const v1::ListModelsResponse& r) {
            if (r.models().empty()) std::cout << "no models (lifemap models upload FILE NAME)\n";
            for (const auto& m : r.models()) PrintModel(m);
          });
    };
  });

  auto* activate = models->add_subcommand(
      "activate",
      "Label frames of a map (or, without --map, of every map without its own) "
      "with a model; --none deactivates");
  auto act_name = std::make_shared<std::string>();
  auto act_map = std::make_shared<std::string>();
  auto none = std::make_shared<bool>(false);
  activate->add_option("NAME", *act_name, "model name");
  activate->add_option("MAP,--map", *act_map,
                       "map (default: the server default; --map MAP: deprecated, as before)");
  activate->add_flag("--none", *none, "deactivate instead (`activate --none [MAP]`)");
  activate->callback([ctx, act_name, act_map, none] {
    ctx->run = [ctx, act_name, act_map, none] {
      // `activate --none MAP`: with --none the one positional is the map.
      if (*none && !act_name->empty()) {
        if (!act_map->empty()) return UsageError("--none takes no model NAME: give only the MAP");
        act_map->swap(*act_name);
      }
      if (act_name->empty() && !*none) {
        return UsageError("give a model NAME, or --none to deactivate");
      }
      return RunCall<v1::ActivateModelResponse>(
          *ctx, [&](client::Client& c) { return c.ActivateModel(*act_name, *act_map); },
          [](const v1::ActivateModelResponse& r) {
            std::cout << Where(r.map()) << ": "
                      << (r.name().empty() ? std::string("no model") : "model '" + r.name() + "'")
                      << (r.previous().empty() ? std::string(" (none before)")
                                               : " (was '" + r.previous() + "')")
                      << "\n";
          });
    };
  });

  auto* del = models->add_subcommand("delete", "Delete a model that is not active anywhere");
  auto del_name = std::make_shared<std::string>();
  del->add_option("NAME", *del_name, "model name")->required();
  del->callback([ctx, del_name] {
    ctx->run = [ctx, del_name] {
      return RunCall<v1::DeleteModelResponse>(
          *ctx, [&](client::Client& c) { return c.DeleteModel(*del_name); },
          [&](const v1::DeleteModelResponse&) {
            std::cout << "deleted model '" << *del_name << "'\n";
          });
    };
  });

  auto* classes =
      models->add_subcommand("classes", "The classes frames of a map are labelled with");
  auto cls_map = std::make_shared<std::string>();
  classes->add_option("MAP,--map", *cls_map,
                      "map (default: the server default; --map MAP: deprecated, as before)");
  classes->callback([ctx, cls_map] {
    ctx->run = [ctx, cls_map] {
      return RunCall<v1::ListClassesResponse>(
          *ctx, [&](client::Client& c) { return c.ListClasses(*cls_map); },
          [&](const v1::ListClassesResponse& r) {
            std::cout << Where(*cls_map) << ": model '" << r.model() << "'\n";
            for (int i = 0; i < r.class_names_size(); ++i) {
              std::cout << absl::StrFormat("  %3d  #%06X  %s\n", i,
                                           i < r.class_colors_size() ? r.class_colors(i) : 0u,
                                           r.class_names(i));
            }
          });
    };
  });
}

}  // namespace lifemap::cli
